"""The emulated Hapkit pantograph: our firmware on two ATmega328P joined on a TWI bus.

The firmware (``firmware_protocol/firmware/pantograph``, one C source built in two roles:
``pantograph_leader.elf``, the TWI master that talks to the host over its UART, and
``pantograph_follower.elf``, the TWI slave driving the second joint) runs cycle by cycle
on two simavr cores inside ``pantograph_board`` (``firmware_protocol/firmware/sim``), which
joins their TWI peripherals (simavr 1.6 models the master only: the board answers for the
slave), wires each board's motor and magnetoresistive sensor to one proximal joint of a
five-bar linkage, integrates the linkage's joint-space dynamics
(:class:`hapsim.joint_device.JointDeviceND` transcribed to C) and bridges the leader's
UART to a pseudo-terminal, in lockstep (the emulated clock waits for each FORCE) or in real
time (the emulated clock locked to the wall clock; a FORCE that misses its tick's DRIVE
slot is applied a tick later and named by the STATEs' ``force_seq``, the known input
:func:`hapsim.pipeline.felt_port.measure_felt_port` takes it as). The leader offers the compact
frames, which :func:`hapsim.pipeline.port_session.handshake_nd` asks for: at 1 kHz they leave a
host 372 us to answer, the full frames none (``docs/pantograph.md``).

The leader is a joint-level device (the Haply 2DIY's division of labour): STATE carries
the joint angles [rad], FORCE the joint torques [N m]; HELLO says so with device id
:data:`DEVICE_ID` and gives the joints' resolution (``position_scale``: rad per sensor
count, ``force_scale``: N m per PWM step). The forward kinematics in float32 on the 16 MHz
AVR took about 20,000 cycles a tick, more than the 16,000 of a 1 kHz period
(``docs/pantograph.md``). :class:`JointLevelTransport` turns it into the Cartesian n-axis
device :func:`hapsim.pipeline.felt_port.measure_felt_port` talks to: handle position
``f(q)`` and torques ``J(q_n)^T F`` with the scene's geometry
(:class:`hapsim.kinematics.Pantograph`), as :class:`hapsim.joint_device.LocalJointDeviceND`
applies them.
"""

from __future__ import annotations

import math

import numpy as np

import firmware_protocol as fp
from hapsim.emulated.hapkit_board import BOARD_DIR, ROOT, make
from hapsim.errors import ConfigError, DeviceError

__all__ = ["FIRMWARE_DIR", "BOARD", "LEADER_ELF", "FOLLOWER_ELF", "DEVICE_ID", "build",
           "board_command", "JointLevelTransport", "wire_term"]

FIRMWARE_DIR = ROOT / "pantograph"
BOARD = BOARD_DIR / "pantograph_board"
LEADER_ELF = FIRMWARE_DIR / "pantograph_leader.elf"
FOLLOWER_ELF = FIRMWARE_DIR / "pantograph_follower.elf"
#: HELLO device id of the pantograph leader ("HKG2" little-endian).
DEVICE_ID = 0x32474B48
#: Sub-step of the board's Runge-Kutta integration [s] (two per 1 kHz period, as
#: :class:`hapsim.joint_device.JointDeviceND`).
SUBSTEP = 5e-4
#: Real time: the longest spin per tick [us] while the board waits for the host's FORCE
#: (``pantograph_board --spin-us``), by default none, as the 1-DoF board: measured beside
#: other work on 2 cores (tools/bench_pantograph.py --realtime), a board spinning up to a
#: period at SCHED_FIFO kept the host's process off its core and 95 % of the ticks late;
#: without the spin 11 % (the FORCE's bytes then reach the UART up to ~150 us after they
#: came, of the compact frames' 372 us of host slack at 1 kHz: docs/pantograph.md).
SPIN_US = 0.0


def build(*, quiet: bool = True) -> dict:
    """Build the two firmware ELFs and ``pantograph_board`` (``make``: only what is missing
    or older than its sources; under the same ``flock`` as :func:`hapsim.emulated.hapkit_board.build`).

    Parameters
    ----------
    quiet : bool
        Capture make's output instead of printing it.

    Returns
    -------
    dict
        ``board``, ``leader``, ``follower`` (paths as str), ``output`` (make's output).

    Raises
    ------
    DeviceError
        A tool is missing or make failed (its output attached).
    """
    output = make("the emulated Hapkit pantograph",
                  ((FIRMWARE_DIR, "all"), (BOARD_DIR, "pantograph_board")), quiet=quiet)
    return {"board": str(BOARD), "leader": str(LEADER_ELF), "follower": str(FOLLOWER_ELF),
            "output": output}


def _pantograph(scene):
    """The scene's pantograph kinematics (ConfigError for another device)."""
    from hapsim.kinematics import device
    dev = scene.device
    if scene.dimension != 2 or dev is None or dev.kind != "pantograph":
        raise ConfigError("the Hapkit pantograph's firmware needs a 2-D scene whose device "
                          f"is a pantograph, not {getattr(dev, 'kind', None)!r}",
                          file=getattr(scene, "path", None), key="device.kind")
    return device("pantograph", dev.geometry)


def board_command(scene, amplitude: float, *, report: str | None = None,
                  link: str | None = None, nack_after: int | None = None,
                  duration: float | None = None, profile: str | None = None,
                  realtime: bool = False, spin_us: float | None = None,
                  host_latency_us: float | None = None) -> list:
    """The ``pantograph_board`` command line for a 2-D pantograph scene.

    Parameters
    ----------
    scene : hapsim.scene.SceneND
        Its device: ``geometry`` (the five-bar's lengths [m]), ``joints`` (the operating
        point [rad]: the home the firmware takes its zero at, written into the leader's
        EEPROM), ``joint_inertia`` [kg m^2] and ``joint_friction`` [N m s/rad] (2 x 2),
        ``hand_mass`` [kg], ``hand_damping`` [N s/m].
    amplitude : float
        The hand's ``a`` [m] (:func:`hapsim.lockstep.excitation_starts`).
    report, link, profile : str, optional
        JSON report written on exit; symbolic link kept to the pty; the leader's cycles
        per flash word.
    nack_after : int, optional
        The follower stops acknowledging from this TWI transaction on (a test of the
        firmware's handling of a lost follower).
    duration : float, optional
        Emulated seconds to run.
    realtime : bool
        Lock the emulated clock to the wall clock (default: lockstep, the clock waits for
        each FORCE).
    spin_us : float, optional
        Real time: the longest spin per tick [us] while the board waits for the host's
        FORCE (emulating in 10 us steps, never ahead of the wall clock by more than one;
        default :data:`SPIN_US`, none: the bytes may then reach the UART up to 150 us after
        they came).

    host_latency_us : float, optional
        Lockstep: each FORCE reaches the leader's UART this long [us] of emulated time
        after the STATE it answers left (an emulated host's answer time).

    Returns
    -------
    list of str

    Raises
    ------
    ConfigError
        Not a 2-D pantograph scene; a non-positive amplitude; a spin outside [0, 1e6]; a
        host latency outside [0, 1e6] or given with ``realtime``.
    """
    kin = _pantograph(scene)
    if not (math.isfinite(amplitude) and amplitude > 0):
        raise ConfigError(f"must be a positive number [m], got {amplitude}", key="--amplitude")
    g = kin.geometry
    dev = scene.device

    def csv(v):
        return ",".join(repr(float(x)) for x in np.ravel(v))
    cmd = [str(BOARD), str(LEADER_ELF), str(FOLLOWER_ELF),
           "--geometry", csv([g.l1, g.l2, g.L1, g.L2, g.d]),
           "--home", csv(dev.joints),
           "--joint-inertia", csv(dev.joint_inertia),
           "--joint-friction", csv(dev.joint_friction),
           "--hand-mass", repr(float(dev.hand_mass)),
           "--hand-damping", repr(float(dev.hand_damping)),
           "--amplitude", repr(float(amplitude)), "--substep", repr(SUBSTEP)]
    for flag, v in (("--report", report), ("--link", link), ("--profile", profile)):
        if v:
            cmd += [flag, v]
    if nack_after is not None:
        cmd += ["--nack-after", str(int(nack_after))]
    if realtime:
        spin = SPIN_US if spin_us is None else float(spin_us)
        if not (math.isfinite(spin) and 0 <= spin <= 1e6):
            raise ConfigError(f"must be in [0, 1e6] us, got {spin_us}", key="--spin-us")
        cmd += ["--realtime", "--spin-us", repr(spin)]
    if host_latency_us is not None:
        lat = float(host_latency_us)
        if realtime or not (math.isfinite(lat) and 0 <= lat <= 1e6):
            raise ConfigError(f"a lockstep host's latency in [0, 1e6] us, got {host_latency_us}",
                              key="host_latency_us")
        cmd += ["--host-latency-us", repr(lat)]
    if duration is not None:
        cmd += ["--duration", repr(float(duration))]
    return cmd


class JointLevelTransport:
    """A joint-level pantograph seen as a Cartesian 2-axis device (module notes).

    Wraps a transport: once the device's HELLO says :data:`DEVICE_ID`, each STATE's joint
    angles ``q`` [rad] become the handle position ``f(q)`` [m] and each FORCE ``F`` [N]
    answering STATE ``n`` becomes the joint torques ``J(q_n)^T F`` [N m] (the Jacobian of
    that STATE's angles, kept in a ring of 256). Before that HELLO, and for any other
    device, messages pass unchanged.

    Parameters
    ----------
    transport : transport of :mod:`hapsim.host.transport`
    scene : hapsim.scene.SceneND
        A 2-D scene whose device is a pantograph (its geometry).

    Attributes
    ----------
    joint_level : bool
        The device said it is the pantograph leader.
    hello : firmware_protocol.Hello or None
    torque_max : float
        The largest joint torque sent [N m] (the wire's term takes its binary32 rounding).
    clamped : int
        STATEs whose torques the firmware clamped (full PWM duty).

    Raises
    ------
    ConfigError
        Not a 2-D pantograph scene.
    """

    def __init__(self, transport, scene) -> None:
        self.inner = transport
        self.kin = _pantograph(scene)
        self.joint_level = False
        self.hello = None
        self._seq = [-1] * 256
        self._J = [(0.0, 0.0, 0.0, 0.0)] * 256
        self.torque_max = 0.0
        self.clamped = 0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def receive(self, timeout: float = 0.0) -> list:
        """The inner transport's messages, STATEs of the pantograph in Cartesian form.

        Parameters
        ----------
        timeout : float
            Longest wait for a first message [s] (the inner transport's).

        Returns
        -------
        list of firmware_protocol messages
            In arrival order; a joint-level pantograph's STATE with its position the
            handle's ``(x, y)`` [m] instead of the joints' [rad].

        Raises
        ------
        hapsim.errors.KinematicsError
            A STATE's joints outside the workspace or at a singularity.
        """
        out = self.inner.receive(timeout)
        for i, m in enumerate(out):
            if isinstance(m, fp.Hello):
                self.joint_level = m.device_id == DEVICE_ID and m.n_axes == 2
                if self.joint_level:
                    self.hello = m
            elif self.joint_level and isinstance(m, fp.State) and len(m.position) == 2:
                q1, q2 = m.position
                x, y = self.kin.forward_at(q1, q2)
                k = m.seq & 255
                self._seq[k] = m.seq
                self._J[k] = self.kin.jacobian_at(q1, q2)
                if m.status & fp.STATUS_FORCE_CLAMPED:
                    self.clamped += 1
                out[i] = fp.State(m.seq, m.time_us, m.status, m.force_seq, (x, y))
        return out

    def send(self, msg) -> None:
        """Send ``msg``; a FORCE as joint torques ``J(q_seq)^T F`` (DeviceError when its
        STATE was not seen).

        Parameters
        ----------
        msg : firmware_protocol message
            A 2-D FORCE's ``force`` is ``(Fx, Fy)`` [N]; any other passes unchanged.

        Raises
        ------
        DeviceError
            A joint-level FORCE whose STATE (its ``seq``) is not in the ring of 256.
        """
        if self.joint_level and isinstance(msg, fp.Force) and len(msg.force) == 2:
            k = msg.seq & 255
            if self._seq[k] != msg.seq:
                raise DeviceError(f"FORCE {msg.seq} answers no STATE seen (joint-level "
                                  "pantograph: its torques need that STATE's Jacobian)")
            j00, j01, j10, j11 = self._J[k]
            fx, fy = msg.force
            t1, t2 = j00 * fx + j10 * fy, j01 * fx + j11 * fy
            self.torque_max = max(self.torque_max, abs(t1), abs(t2))
            msg = fp.Force(msg.seq, (t1, t2))
        self.inner.send(msg)


def wire_term(scene, res: dict, rad_per_count: float, torque_step: float) -> dict:
    """The wire's term of the stated uncertainty for the emulated Hapkit pantograph.

    As :func:`hapsim.emulated.haply2_verdict.felt_verdict_of_runs` for the 2DIY, with this
    device's resolution: each joint angle is read to within ``delta = c / 2`` plus one
    binary32 ulp of the angle (the count rounded, then ``home + n c`` in single
    precision), each torque reaches the joint to within half a PWM step
    ``s / 2`` (the firmware rounds ``|tau| / s`` to the nearest step) plus the binary32
    rounding of the torque (relative ``2^-24``). Each error moves the records through the
    loop (:func:`hapsim.lockstep.error_responses`: the joint errors reach the handle
    through ``J(q0)``, the torque errors through ``J(q0)^-T``) and the fit to first order
    (:func:`hapsim.analysis.pencil.felt_sensitivity_nd`); their worst case, whatever
    their signs and correlation (:func:`hapsim.analysis.pencil.worst_case_nd`; the
    rest record's errors enter every difference), taken at the records and at each
    statement's worst errors within the bounds, the largest times a margin
    (:func:`hapsim.analysis.wire_box.box_worst_case`), over the predicted matrix's
    largest entry, is the term. The first-order term at the records alone is no bound:
    on configs/pantograph_spring.yaml at 5 mm (the loop in lockstep, this device's
    counts), errors within the bounds, each statement's worst signs re-linearised at the
    records they moved, moved the felt damping 1.7 times its first-order term (0.34
    against 0.20) and along x 1.9 times (0.35 against 0.18), terms that stated it;
    over the box that scene states nothing through this firmware in lockstep
    (tests/test_pantograph_spring.py, tests/test_wire_box_devices.py).

    Parameters
    ----------
    scene : hapsim.scene.SceneND
    res : dict
        :func:`hapsim.pipeline.felt_port.measure_felt_port`'s result (``responses``,
        ``samples``, ``predicted``, ``order``) and ``torque_max`` [N m] (the largest
        torque sent: :attr:`JointLevelTransport.torque_max`).
    rad_per_count : float
        ``c``: joint angle per sensor count [rad] (HELLO ``position_scale``).
    torque_step : float
        ``s``: joint torque per PWM step [N m] (HELLO ``force_scale``).

    Returns
    -------
    dict
        ``felt_stiffness``, ``felt_damping`` (relative; inf when the records, or a copy
        moved within the bounds, give no sensitivity), ``directions`` (the terms along
        each principal direction), ``first_order`` (the same at the records alone:
        :func:`hapsim.lockstep.wire_terms_nd` with ``box=True``), ``reading_bound_rad`` (per joint),
        ``torque_bound_nm``, ``quantum_m`` (one count at the handle, ``|J(q0)|_2 c`` [m]).
    """
    from hapsim.lockstep import wire_terms_nd
    kin = _pantograph(scene)
    q0 = np.asarray(scene.device.joints, float)
    J = kin.jacobian(q0)
    recs = res["responses"]
    diffs = [r - recs[0] for r in recs[1:]]
    ulp = np.spacing(np.abs(q0).astype(np.float32)).astype(float)
    delta = rad_per_count / 2.0 + ulp
    tmax = abs(float(res.get("torque_max", 0.0)))
    tbound = torque_step / 2.0 + 2.0 ** -24 * tmax
    out = {"reading_bound_rad": delta.tolist(), "torque_bound_nm": tbound,
           "quantum_m": float(np.linalg.norm(J, 2) * rad_per_count)}
    out.update(wire_terms_nd(scene, diffs, res["predicted"], res["order"],
                             [("reading", J, delta),
                              ("force", np.linalg.inv(J).T, np.full(2, tbound))],
                             box=True))
    return out
