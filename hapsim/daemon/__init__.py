"""The hapsim daemon: mock device, transports, fixed-rate host loop, runner, telemetry.

Modules
-------
:mod:`hapsim.daemon.mock`
    The device side of the protocol with exact THS physics (``MockPhysics``,
    ``MockDevice``) and its serving loops (lockstep / real-time) on a file descriptor.
:mod:`hapsim.daemon.transport`
    Message transports seen from the host: in-process (no bytes), pyserial (pty or
    hardware), and the embedded mock on a pseudo-terminal.
:mod:`hapsim.daemon.loop`
    The host loop: handshake, device- or host-clocked fixed-rate loop, safety.
:mod:`hapsim.daemon.telemetry`
    Preallocated per-sample telemetry and its atomic writer.
:mod:`hapsim.daemon.runner`
    ``run_scene``: calibrate, check, close the THS, identify, report.

Timing convention (DESIGN §4): STATE ``n`` carries ``x(nT)``; the FORCE answering it
(``seq = n``) is computed from ``x[n]`` and ``x[n-1]`` and applied by the device over
``[(n+d)T, (n+d+1)T)`` with a zero-order hold; ``d = 0`` (apply at once) exists in lockstep only.
"""
