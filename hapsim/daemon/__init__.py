"""The hapsim daemon: mock device, transports, fixed-rate host loop, runner, telemetry.

Modules
-------
:mod:`hapsim.daemon.mock`
    The device side of the protocol (``MockDevice``) around the device model
    (:mod:`hapsim.device_model`: ``MockPhysics``) and its serving loops (lockstep /
    real-time) on a file descriptor.
:mod:`hapsim.daemon.transport`
    Message transports seen from the host: in-process (no bytes), pyserial (pty or
    hardware), the embedded mock on a pseudo-terminal, and the real-time mock on a virtual
    clock (``SimTransport``, for fault tests).
:mod:`hapsim.daemon.faults`
    Seeded fault injection for the mock (``FaultPlan``, ``parse_faults``, SPEC syntax):
    dropped, corrupted, duplicated, reordered, delayed frames, garbage, stall, reset, port
    vanishing, no HELLO.
:mod:`hapsim.daemon.loop`
    The host loop: device- or host-clocked fixed-rate loop, safety (limits, passivity
    observer/controller); its handshake (:mod:`hapsim.daemon.handshake`), recovery of a
    lost device (:mod:`hapsim.daemon.recovery`), bad-frame records
    (:mod:`hapsim.daemon.bad_frames`), configuration and result
    (:mod:`hapsim.daemon.loop_types`).
:mod:`hapsim.daemon.fastloop`
    The device-clocked loop compiled with numba (its I/O primitives:
    :mod:`hapsim.daemon.compiled_io`).
:mod:`hapsim.daemon.telemetry`
    Preallocated per-sample telemetry (a head kept whole, then a ring: runs may be
    open-ended), its chunked journal (writer thread draining the ring, loss/recovery events,
    ``load``) and the atomic ``.npz``/``.csv`` export.
:mod:`hapsim.daemon.runner`
    ``run_scene``: calibrate, check, close the THS, identify, report (the prediction and
    the measurement are :mod:`hapsim.analysis.prediction` and
    :mod:`hapsim.analysis.measurement`); its steps' results are the records of
    :mod:`hapsim.daemon.run_types`, its identification step :mod:`hapsim.daemon.measure`.
:mod:`hapsim.daemon.options`
    ``RunOptions``: the options of one run, built once.
:mod:`hapsim.daemon.report`
    ``build_report``: a run's report dict; ``format_report``: its human lines.

Timing convention (docs/design.md, 'The timing convention'): STATE ``n`` carries
``x(nT)``; the FORCE answering it (``seq = n``) is computed from ``x[n]`` and ``x[n-1]``
and applied by the device over ``[(n+d)T, (n+d+1)T)`` with a zero-order hold; ``d = 0``
(apply at once) exists in lockstep only.
"""
