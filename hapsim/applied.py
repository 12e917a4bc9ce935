"""One account of the force a device applied at every tick (identify, run's measurement).

A device runs on its own clock, behind a serial line whose latency varies: the FORCE
answering STATE ``n`` is applied at tick ``n + d`` when it arrives in time, and when it does
not the device holds the force it applied before (a *late* tick). A late tick is not noise:
the framed protocol's STATE carries ``force_seq``, the ``seq`` of the FORCE applied from
that tick on (``firmware_protocol/PROTOCOL.md`` §1, §4), so the host knows the force held
over every period and the delay the device really has, ``seq - force_seq``. With that
account, a record with late ticks is a linear time-invariant loop driven by a known input:
the force the device applied, i.e. the force computed plus the known disturbance
``applied - computed`` (:func:`hapsim.analysis.error_response.disturbance_response`).

Two sources give the account:

- :func:`account_from_force_seq` (the framed protocol): exact. ``applied[k]`` is the force
  the host sent answering the STATE whose ``seq`` is STATE ``k``'s ``force_seq`` (0 before
  the device applied any, or when its watchdog zeroed the force); the device's delay is the
  smallest ``seq - force_seq`` it showed on a tick that applied a FORCE (a device never
  applies a force before it is due; a late tick only shows a larger one). Which FORCE a
  STATE names and whether its tick is late is the rule of :mod:`hapsim.kernels.ticks`,
  the same functions the Python and the compiled host loops count late ticks with.
- :func:`account_from_timing` (drivers whose protocol has no such field: FireFader, Haply,
  Hapkit-serial): the host's own clock says which force was written before each record was
  read; where it cannot tell (``ambiguous``: the write and the device's tick too close to
  order) the applied force is one of two, and the account states the half-difference as
  ``half_width`` [N]. The drivers fill ``ambiguous`` from their timing.

Either way the result is an :class:`AppliedAccount`, which the fit of the device
(:func:`hapsim.analysis.device_fit.fit_device`) and the closed-loop measurement use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# the STATE.status bits read here, the protocol's own (firmware_protocol imports nothing of
# hapsim: it stands on the ground floor with this module)
from firmware_protocol.codec import (STATUS_FORCE_APPLIED, STATUS_FORCE_CLAMPED,
                                     STATUS_OVERRUN, STATUS_WATCHDOG_TRIPPED)
from hapsim.kernels.ticks import late_ticks

__all__ = ["AppliedAccount", "account_from_force_seq", "account_from_timing", "firmware_force",
           "STATUS_WATCHDOG_TRIPPED", "STATUS_FORCE_CLAMPED", "STATUS_FORCE_APPLIED",
           "STATUS_OVERRUN"]


@dataclass
class AppliedAccount:
    """The force a device held over each period of a record.

    Attributes
    ----------
    applied : ndarray, shape (n,)
        Force held over ``[kT, (k+1)T)`` [N] (row ``k`` of the record).
    source : ndarray of int64, shape (n,)
        Row whose sent force that is; -1 when no sent force is held (none applied yet,
        watchdog) or the row is not in the record.
    tick_delay : ndarray of int64, shape (n,)
        ``seq - force_seq`` the device showed at each row [samples]; -1 where unknown.
    delay : int
        The device's delay d [samples]: the smallest ``tick_delay`` of a row that applied
        a FORCE (-1 when the record shows none).
    late : ndarray of bool, shape (n,)
        Rows whose held force is not the one answering the STATE ``d`` ticks before (an
        older one, or zero from the device's watchdog).
    half_width : ndarray, shape (n,)
        Bound on ``|applied_true - applied|`` [N] (0 throughout from ``force_seq``).
    known : ndarray of bool, shape (n,)
        Rows whose applied force the account knows (to ``half_width``); an unknown row
        holds a force sent before the record began, or one the device may have parsed
        from the wrong bytes (:meth:`hapsim.drivers.base.Driver.unknown_force_rows`).
        The device fit leaves unknown rows out; so does the closed-loop measurement of a
        driver's run (:func:`hapsim.analysis.measurement.late_accounted` names them, and
        the record is cut there).
    method : str
        ``"force_seq"``, ``"timing"`` or ``"lockstep"``.
    """

    applied: np.ndarray
    source: np.ndarray
    tick_delay: np.ndarray
    delay: int
    late: np.ndarray
    half_width: np.ndarray
    known: np.ndarray
    method: str

    @property
    def n_late(self) -> int:
        """Late rows (int)."""
        return int(np.count_nonzero(self.late))

    def rows(self, a: int, b: int) -> "AppliedAccount":
        """The account of rows ``[a, b)`` (sources renumbered from ``a``; a source before
        ``a`` stays known through ``applied``, its index becomes -1).

        Parameters
        ----------
        a, b : int
            First row and the row past the last (slice bounds, >= 0).

        Returns
        -------
        AppliedAccount
            Copies of the rows' arrays; the same ``delay`` and ``method``.
        """
        src = self.source[a:b] - a
        return AppliedAccount(self.applied[a:b].copy(), np.where(src >= 0, src, -1),
                              self.tick_delay[a:b].copy(), self.delay, self.late[a:b].copy(),
                              self.half_width[a:b].copy(), self.known[a:b].copy(),
                              self.method)

    def to_dict(self) -> dict:
        """Summary for a report: ``method``, ``delay``, ``late``, ``rows``,
        ``tick_delay_max``, ``unknown`` (rows), ``half_width_max`` [N].

        Returns
        -------
        dict
            Those fields, JSON-ready: ints (``tick_delay_max`` -1 with none known),
            ``method`` a str, ``half_width_max`` a float (0 with no rows).
        """
        td = self.tick_delay[self.tick_delay >= 0]
        return {"method": self.method, "delay": int(self.delay), "late": self.n_late,
                "rows": int(self.applied.size),
                "tick_delay_max": int(td.max()) if td.size else -1,
                "unknown": int(np.count_nonzero(~self.known)),
                "half_width_max": float(self.half_width.max()) if self.half_width.size
                else 0.0}

    def disturbance(self, force, seq=None) -> np.ndarray:
        """The known disturbance of a loop: the applied force minus the force that an
        on-time device would have held, ``w[k] = applied[k] - force[k - d]`` [N].

        Parameters
        ----------
        force : array_like, shape (n,)
            Force sent answering each row [N] (the loop's ``F``).
        seq : array_like of int, shape (n,), optional
            STATE seq of each row: ``w`` is then computed on each stretch of consecutive
            seq on its own, and is 0 at a stretch's first ``d`` rows (the forces in
            flight there are the loop's state at the stretch's start, not a disturbance).

        Returns
        -------
        ndarray, shape (n,)
            ``w`` (0 for ``k < d``).
        """
        f = np.asarray(force, float)
        n = f.size
        d = max(self.delay, 0)
        w = np.zeros(n)
        if seq is None:
            bounds = [(0, n)]
        else:
            s = np.asarray(seq, np.int64)
            cuts = np.flatnonzero(np.diff(s) != 1) + 1
            e = np.concatenate([[0], cuts, [n]])
            bounds = list(zip(e[:-1], e[1:]))
        for a, b in bounds:
            if b - a > d:
                w[a + d:b] = self.applied[a + d:b] - f[a:b - d]
        return w


def _rows_of(seq: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Row ``j <= k`` with ``seq[j] == src[k]`` for each ``k`` (-1 where none).

    ``seq`` increases by at least 1 per row inside a stretch; a fall (a recovery restarts
    the device's ticks) starts a new stretch, searched on its own.
    """
    n = seq.size
    out = np.full(n, -1, dtype=np.int64)
    cuts = np.flatnonzero(np.diff(seq) <= 0) + 1
    bounds = np.concatenate([[0], cuts, [n]]).astype(np.int64)
    for a, b in zip(bounds[:-1], bounds[1:]):
        s = seq[a:b]
        want = src[a:b]
        j = np.searchsorted(s, want)
        ok = (want >= 0) & (j < s.size)
        jj = np.where(ok, j, 0)
        ok &= s[jj] == want
        ok &= jj <= np.arange(b - a)
        out[a:b] = np.where(ok, a + jj, -1)
    return out


def firmware_force(force, force_scale: float, force_limit: float = np.inf) -> np.ndarray:
    """The force a framed device with an actuator resolution applies for each force sent,
    in the Hapkit firmware's own arithmetic (``firmware_protocol/firmware/hapkit/main.c``,
    ``take_force`` and ``on_config``), bit for bit.

    The firmware computes in binary32: the FORCE's binary64 rounded to binary32 (nearest,
    ties to even; beyond the range: infinite, clamped below), ``ax = |x| * c`` with
    ``c = (float)(steps / force_max)``, and the step ``n = (uint16_t)(ax + 0.5f)`` (the
    sum rounded to binary32, then truncated): not the binary64 nearest multiple, which
    names another step near a half-step. The clamp: ``n`` is at most
    ``floor(limit * c)``. ``c`` is restored from ``HELLO.force_scale`` (the binary32
    ``force_max / steps``, sent widened): ``1.0f / scale`` is the same binary32 as
    ``steps / force_max`` (``steps`` is a power of two, so the quotients differ by an
    exact factor and round alike).

    Parameters
    ----------
    force : array_like, shape (n,)
        Forces sent [N].
    force_scale : float > 0
        HELLO.force_scale [N/step].
    force_limit : float
        The effective force limit [N] (``min(CONFIG, HELLO)``); inf: none.

    Returns
    -------
    ndarray, shape (n,)
        ``sign(x) * n * force_scale`` [N] (NaN stays NaN; an infinite force with no
        finite limit stays infinite).

    Raises
    ------
    ValueError
        ``force_scale`` not > 0.
    """
    if not force_scale > 0:
        raise ValueError(f"force_scale must be > 0, got {force_scale!r}")
    f32 = np.float32
    with np.errstate(over="ignore", invalid="ignore"):
        x = np.asarray(force, np.float64).astype(f32)
        c = f32(1.0) / f32(force_scale)
        ax = np.abs(x) * c                                   # binary32 product
        n = np.floor(ax + f32(0.5))                          # binary32 sum, truncated
        if np.isfinite(force_limit):
            lim_n = np.floor(f32(force_limit) * c)           # on_config: floor(limit * c)
            n = np.minimum(n, lim_n)
        out = np.sign(x).astype(np.float64) * n.astype(np.float64) * float(force_scale)
    return out


def account_from_force_seq(seq, force, force_seq, status, *, zero_delay: bool = False,
                           force_limit: float = np.inf, force_scale: float = 0.0
                           ) -> AppliedAccount:
    """The account of a framed device from its STATEs (module notes).

    Parameters
    ----------
    seq : array_like of int, shape (n,)
        STATE.seq of each row (u32 values; the record's rows in order).
    force : array_like, shape (n,)
        Force the host sent answering row ``k`` [N].
    force_seq : array_like of int, shape (n,)
        STATE.force_seq of each row (u32; -1 where the protocol carries none).
    status : array_like of int, shape (n,)
        STATE.status bits of each row.
    zero_delay : bool
        The device applies FORCE ``n`` over ``[nT, (n+1)T)`` (``d = 0``, the lockstep mock
        only): its STATE ``n`` cannot name that force yet (it names the previous period's),
        so the applied force is the one sent at the same row.
    force_limit : float
        The device's effective force limit [N] (``min(CONFIG, HELLO)``): a row with
        STATUS_FORCE_CLAMPED holds the force clamped there.
    force_scale : float
        Actuator resolution [N] (HELLO.force_scale; 0: none): the applied force is the
        step the firmware's binary32 arithmetic names (:func:`firmware_force`).

    Returns
    -------
    AppliedAccount
        ``method = "force_seq"`` (``"lockstep"`` with ``zero_delay``).

    Raises
    ------
    ValueError
        Columns of different lengths.
    """
    seq = np.asarray(seq, np.int64)
    f = np.asarray(force, float)
    fseq = np.asarray(force_seq, np.int64)
    st = np.asarray(status, np.int64)
    n = seq.size
    if not (f.shape == fseq.shape == st.shape == (n,)):
        raise ValueError(f"columns of different lengths: {seq.shape}, {f.shape}, "
                         f"{fseq.shape}, {st.shape}")
    if force_scale and force_scale > 0:
        f = firmware_force(f, force_scale, force_limit)
    if zero_delay:
        tick = np.empty(n, np.int64)
        late = np.zeros(n, bool)
        late_ticks(seq, fseq, st, 0, False, tick, late, np.zeros(n, bool))
        src = np.arange(n, dtype=np.int64)
        # an overrun holds the previous period's force
        for k in np.flatnonzero(late):
            src[k] = src[k - 1] if k > 0 else -1
        applied = np.where(src >= 0, f[np.maximum(src, 0)], 0.0)
        return AppliedAccount(applied, src, np.zeros(n, np.int64), 0, late, np.zeros(n),
                              np.ones(n, bool), "lockstep")
    # the late-tick rule (hapsim.kernels.ticks), as the host loops read it: which FORCE
    # each row names (a running OR of FORCE_APPLIED says whether the device sets the bit)
    # (the whole record says whether the device sets the bit at all, kernels.ticks notes)
    uses_bit = bool(np.any(st & STATUS_FORCE_APPLIED))
    tick = np.empty(n, np.int64)
    late = np.zeros(n, bool)
    flags = np.zeros(n, bool)
    late_ticks(seq, fseq, st, -1, uses_bit, tick, late, flags)
    named = tick >= 0
    wd = (st & STATUS_WATCHDOG_TRIPPED) != 0
    src_seq = np.where(named, seq - tick, -1)
    src = _rows_of(seq, src_seq)
    applied = np.where(src >= 0, f[np.maximum(src, 0)], 0.0)
    applied = np.where(wd, 0.0, applied)
    if np.isfinite(force_limit):
        cl = (st & STATUS_FORCE_CLAMPED) != 0
        applied = np.where(cl, np.clip(applied, -force_limit, force_limit), applied)
    # the device's delay: the smallest it shows on a tick that applied a FORCE (a device
    # never applies one before it is due; a late tick only shows a larger one)
    # (force_seq = 0 without FORCE_APPLIED is "FORCE 0 or none yet", kernels.ticks notes:
    # it shows a delay only when no row says more)
    on = named & ~wd
    sure = on & ~((fseq == 0) & ((st & STATUS_FORCE_APPLIED) == 0))
    on = sure if np.any(sure) else on
    d = int(tick[on].min()) if np.any(on) else -1
    # known: a named force in the record, or none named (zero) before the first one
    first = int(np.argmax(named)) if np.any(named) else n
    idx = np.arange(n)
    known = (named & (src >= 0)) | wd | (~named & (idx < first))
    if d >= 0:
        late_ticks(seq, fseq, st, d, uses_bit, tick, late, flags)
    src = np.where(wd, -1, src)
    return AppliedAccount(applied, src, tick, d, late, np.zeros(n), known, "force_seq")


def account_from_timing(force, delay: int, *, late=None, ambiguous=None,
                        force_scale: float = 0.0, quantise=None,
                        stage_half_width=None) -> AppliedAccount:
    """The account of a device whose protocol names no applied force (module notes).

    Parameters
    ----------
    force : array_like, shape (n,)
        Force the host sent answering row ``k`` [N] (the protocol's quantised value).
    delay : int >= 0
        Ticks between a record and the force answering it acting, by the driver's timing
        [samples].
    late : array_like of bool, shape (n,), optional
        Rows where the driver's clock shows the answer missed its tick (the force before
        is held).
    ambiguous : array_like of bool, shape (n,), optional
        Rows where the driver's clock cannot order the write and the device's tick: the
        held force is the on-time one or the one before; the account takes their middle
        and states the half-difference in ``half_width`` (a bound on the error either way).
    force_scale : float
        Actuator resolution [N] (0: none): without ``quantise``, the nearest multiple.
    quantise : callable, optional
        The driver's own rule on the whole array, forces sent [N], shape (n,) -> forces
        the device receives [N], shape (n,) (its
        :meth:`~hapsim.drivers.base.Driver.applied_forces`, the arithmetic its protocol
        encodes with); it replaces ``force_scale``'s nearest multiple.
    stage_half_width : array_like, shape (n,), optional
        How far each force in ``force`` is uncertain [N] (a board's output stage whose
        level the firmware's rounding may name either way:
        :meth:`hapsim.drivers.base.Driver.output_stage`); carried to the rows that hold
        it (an ambiguous row: the larger of its two forces').

    Returns
    -------
    AppliedAccount
        ``method = "timing"``; ``tick_delay`` is ``delay`` (``delay + 1`` where late).

    Raises
    ------
    ValueError
        A negative delay, arrays of different lengths.
    """
    f = np.asarray(force, float)
    n = f.size
    d = int(delay)
    if d < 0:
        raise ValueError(f"delay must be >= 0, got {delay!r}")
    if quantise is not None:
        f = np.asarray(quantise(f), dtype=np.float64).reshape(f.shape)
    elif force_scale and force_scale > 0:
        f = np.round(f / force_scale) * force_scale
    lt = np.zeros(n, bool) if late is None else np.asarray(late, bool)
    amb = np.zeros(n, bool) if ambiguous is None else np.asarray(ambiguous, bool)
    if lt.shape != (n,) or amb.shape != (n,):
        raise ValueError("force, late and ambiguous must have one length")
    idx = np.arange(n, dtype=np.int64)
    src = idx - d
    for k in np.flatnonzero(lt):
        src[k] = src[k - 1] if k > 0 else -1
    src = np.where(src >= 0, src, -1)
    applied = np.where(src >= 0, f[np.maximum(src, 0)], 0.0)
    prev = np.where(src >= 1, f[np.maximum(src - 1, 0)], 0.0)
    # an ambiguous row holds the on-time force or the one before: the middle of the two,
    # and half their difference bounds |applied_true - applied| (the on-time one stated
    # with that half-width would leave the other case outside)
    hw = np.where(amb, 0.5 * np.abs(applied - prev), 0.0)
    applied = np.where(amb, 0.5 * (applied + prev), applied)
    if stage_half_width is not None:
        sh = np.asarray(stage_half_width, float).reshape(f.shape)
        own = np.where(src >= 0, sh[np.maximum(src, 0)], 0.0)
        before = np.where(src >= 1, sh[np.maximum(src - 1, 0)], 0.0)
        hw = hw + np.where(amb, np.maximum(own, before), own)
    tick = np.where(lt, d + 1, d).astype(np.int64)
    return AppliedAccount(applied, src, tick, d, lt, hw, np.ones(n, bool), "timing")
