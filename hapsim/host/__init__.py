"""The host side of the wire: the fixed-rate host loop, its compiled twin, its transports.

Modules
-------
:mod:`hapsim.host.loop`
    The host loop: device- or host-clocked fixed-rate loop, safety (limits, passivity
    observer/controller); its handshake (:mod:`hapsim.host.handshake`), recovery of a
    lost device (:mod:`hapsim.host.recovery`), bad-frame records
    (:mod:`hapsim.host.bad_frames`), configuration and result
    (:mod:`hapsim.host.loop_types`), the link's verdict (:mod:`hapsim.host.link_verdict`),
    real-time priority and sleeping (:mod:`hapsim.host.realtime`).
:mod:`hapsim.host.fastloop`
    The device-clocked loop compiled with numba (its I/O primitives:
    :mod:`hapsim.kernels.compiled_io`, shared with the compiled mock).
:mod:`hapsim.host.transport`
    Message transports seen from the host: in-process (no bytes), pyserial (pty or
    hardware), the embedded mock on a pseudo-terminal, and the real-time mock on a virtual
    clock (``SimTransport``, for fault tests). The device families' own links are
    :mod:`hapsim.drivers.transport`.
:mod:`hapsim.host.telemetry`
    Preallocated per-sample telemetry (a head kept whole, then a ring: runs may be
    open-ended), its chunked journal (writer thread draining the ring, loss/recovery events,
    ``load``) and the atomic ``.npz``/``.csv`` export.
:mod:`hapsim.host.correction`
    The engine corrected for the loop's delay and hold (``corrected_engine``).

What pretends to be hardware (mocks, emulated boards, fault injection) is
:mod:`hapsim.emulated`; one run's pipeline (calibrate, check, close the THS, identify,
report) is :mod:`hapsim.pipeline`.

Timing convention (docs/design.md, 'The timing convention'): STATE ``n`` carries
``x(nT)``; the FORCE answering it (``seq = n``) is computed from ``x[n]`` and ``x[n-1]``
and applied by the device over ``[(n+d)T, (n+d+1)T)`` with a zero-order hold; ``d = 0``
(apply at once) exists in lockstep only.
"""
