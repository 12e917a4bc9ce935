"""The device side of the wire: everything that pretends to be hardware.

Each model keeps its own (wall-clock) time unless a caller asks for lockstep by name
(docs/drivers.md, docs/mock.md).

Modules
-------
:mod:`hapsim.emulated.mock`
    The mock device of the framed protocol (``MockDevice``) around the device model
    (:mod:`hapsim.device_model`: ``MockPhysics``); its serving loop (lockstep / real-time)
    on a file descriptor :mod:`hapsim.emulated.serve`; its compiled tick
    :mod:`hapsim.emulated.fastmock`; and, in the same module, its n-DoF
    twin ``MockDeviceND``.
:mod:`hapsim.emulated.faults`
    Seeded fault injection for the mock (``FaultPlan``, ``parse_faults``, SPEC syntax):
    dropped, corrupted, duplicated, reordered, delayed frames, garbage, stall, reset, port
    vanishing, no HELLO.
:mod:`hapsim.emulated.driver_mock`
    The device families' boards (FireFader, Haply, Hapkit-serial) byte for byte on a
    pseudo-terminal.
:mod:`hapsim.emulated.haply2_board`
    The Haply 2DIY's board (firmware V1.5's parser, a pantograph as the plant).
:mod:`hapsim.emulated.falcon_device`, :mod:`hapsim.emulated.ftdi_usb`
    The Novint Falcon (loader, firmware loop, homing, the delta) behind an emulated FTDI
    FT232R on pyusb's backend interface.
:mod:`hapsim.emulated.hapkit_board`, :mod:`hapsim.emulated.pantograph_board`
    The Hapkit 3 and the Hapkit pantograph: our firmware built with avr-gcc, run on simavr.
"""
