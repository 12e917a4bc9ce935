"""The Haply 2DIY record loop's limits (:func:`hapsim.pipeline.haply2_record.record_realtime`):
its waits, its bounds on a torque held and on the joints' motion, and the host watchdog's
robust write for the 2DIY (:func:`watchdog_robust`). Each limit says where its figure
comes from; :mod:`hapsim.pipeline.haply2_record`'s notes say how the loop uses them.
"""

from __future__ import annotations

import math

from hapsim.drivers.haply import LONGEST_COMMAND
from hapsim.drivers.haply2 import Haply2DIY

__all__ = ['ARM_TIMEOUT', 'QUIET_S', 'SPIN_S', 'SILENT_WRITES', 'ARM_TRIES', 'REARM_WAIT_S', 'REPLY_WAIT_S', 'END_WAIT_S', 'HOLD_BOUND_S', 'SILENT_S', 'ENVELOPE_RAD', 'WORKSPACE_RAD', 'REARM_REPLY_S', 'REARM_QUIET_S', 'REARM_SENDS', 'AWAKE_GAP_S', 'watchdog_robust']

#: Longest wait for the first reply after a set-up [s] (a board process just started
#: loads its compiled plant first).
ARM_TIMEOUT = 10.0
#: Silence that ends the draining before a set-up [s].
QUIET_S = 0.03
#: How long before a tick's deadline the host stops sleeping and polls [s].
SPIN_S = 3e-4
#: Writes in a row without a reply after which the real-time loop re-synchronises the
#: board (:class:`hapsim.drivers.haply.ResyncRule`): more than the longest command the
#: board can be inside swallows (:data:`hapsim.drivers.haply.LONGEST_COMMAND` bytes, 10
#: a write); after that a board out of step answers something, which the decoder's
#: desync sees sooner. A slow board (a loaded host's child process) is not taken for
#: one out of step before this.
SILENT_WRITES = LONGEST_COMMAND // 10 + 1
#: Set-ups tried in a row before the loop gives up on a stream that corrupts them.
ARM_TRIES = 5
#: Longest wait for a re-armed board's answer to the zero write before its set-up [s]
#: (a board out of step may be inside a command that swallows it).
REARM_WAIT_S = 0.05
#: Longest wait for the first reply of a set-up after the first [s] (the board runs).
REPLY_WAIT_S = 0.2
#: Longest wait for the reply to a record's closing zero write [s] (without it, the
#: board is re-armed: a loaded host must not take a slow reply for a lost one).
END_WAIT_S = 1.0
#: Longest time [s] the host lets the board (no watchdog) hold a torque computed from a
#: sample older than this: an estimated tick past it writes zero torque (``held_zero``).
#: The same bound as the 1-DoF driver's (:data:`hapsim.drivers.resync.HOLD_BOUND_S`).
HOLD_BOUND_S = 0.02
#: The oldest unanswered write's wait [s] that shows the board stopped answering (with
#: more than :data:`SILENT_COUNT` unanswered): a board answers a write within its pass and
#: a USB frame, about 1 ms; a late reply or a host stall is not this. The hold bound: a
#: board out of step may hold a torque a garbage command set, and it is re-synchronised
#: (zero torque) no later than this after the write it stopped answering (before, after
#: :data:`SILENT_WRITES` writes: 56 ms at 1 kHz, in which 0.123 N m turns a 2e-4 kg m^2
#: joint 0.96 rad and leaves it at 34 rad/s).
SILENT_S = HOLD_BOUND_S
#: The measurement's envelope [rad]: a reading of either joint farther than this from
#: the scene's operating point ends the record's torque loop (zero torque written from
#: that tick on, the record "left" and not measured). The hand moved the handle 1e-4 m
#: (about 1e-3 rad): the records' largest joint motion measured, on the wall clock and
#: unloaded, 0.0095 rad; three times that. The run's designed start
#: (:func:`hapsim.commands.run_haply2.designed_start`) keeps the exact records within
#: 0.9 of it through ``J(q0)``'s smallest singular value, a bound: on
#: docs/pantograph_deep_wall.yaml, envelope-limited at 0.54 mm, the joints moved at most
#: 0.0146 rad over the driver table's 20 runs, bytes lost included. Beside two CPU-bound
#: processes a host on a third of its rate took a correct loop's record to 0.5 rad (no
#: fault, the board on its own clock) before any bound, and with 0.1 rad the light joint
#: (2e-4 kg m^2) coasted on to 0.69 and 0.86 rad after the zero torque.
ENVELOPE_RAD = 0.03
#: The joints' workspace in a measurement [rad]: the largest departure of either joint
#: from the scene's operating point a run may reach (the emulated board's truth,
#: ``excursion``, is held to it by the tests). The hand's records move the handle
#: 0.1-1.2 mm (the designed start; about 1e-3 to 2e-2 rad); a 30 ms host stall at the
#: board's clamp turns this 2e-4 kg m^2 joint 1/2 (0.123/2e-4) 0.03^2 = 0.28 rad; the
#: five-bar of configs/pantograph_wall.yaml reaches its singular boundary 0.78 rad from
#: rest (either joint): 0.5 rad is inside it with a margin of 1.5. The braking after the
#: joints left :data:`ENVELOPE_RAD` ends when the coast friction alone would still give
#: is 1 % of it (:func:`hapsim.braking.brake_rest`).
WORKSPACE_RAD = 0.5
#: Longest wait [s] for a re-armed board's evidence that it took the re-arming (its
#: answer to the closing zero write reading the set-up's offsets) before the re-arming is
#: sent again, zero torque first: the hold bound (the board has no watchdog: a torque a
#: garbage command set is held until a write in step replaces it) plus the set-up's own
#: two encoders' 2 ms waits (:data:`hapsim.emulated.haply2_board.SETUP_S`). Before, a
#: re-arming whose bytes the stream corrupted waited up to 0.25 s with the clamp's 0.123 N m
#: held: 16.8 rad of true excursion with 1 byte in 200 lost.
REARM_REPLY_S = HOLD_BOUND_S + 4e-3
#: Quiet [s] after a re-arming's evidence before its sample's zero write: the set-up's
#: two encoders' waits (a reply that read the offsets may have been the first zero
#: write's, the closing one still to come after the set-up).
REARM_QUIET_S = 5e-3
#: Re-armings sent in a row for want of that evidence before the loop gives up (each
#: 62 + LONGEST_COMMAND bytes, each at most REARM_REPLY_S of host time awake).
REARM_SENDS = 20
#: Longest gap [s] between two polls of the host that counts as the host awake: a wait is
#: measured in the time the host was polling, so a host stall (the host descheduled, not
#: reading) is never taken for a board's silence.
AWAKE_GAP_S = 2e-3


def watchdog_robust(driver: Haply2DIY, scene) -> tuple:
    """The 2DIY's robust write for the host's watchdog
    (:class:`hapsim.drivers.torque_watchdog.TorqueWatchdog`'s ``robust``): the loop's own
    re-arming at the scene's operating point (:meth:`hapsim.drivers.haply2.Haply2DIY.
    arm_bytes`: a zero write, :data:`~hapsim.drivers.haply.LONGEST_WAIT` zero bytes, two
    bytes 3, the set-up, a zero write; zero torque whatever the board's parser is inside),
    carrying no value.

    Fixed arming offsets, not the joints last read: the set-up carries two encoder
    offsets, and the loop re-arms at the operating point (module notes: the emulated
    board's hand holds the handle there at each set-up; a real board's angles are then off
    by the motion since the arming, within :data:`ENVELOPE_RAD`). A live host follows the
    watchdog's set-up with a re-arming of its own (:func:`record_realtime`), so the angles
    the board reads after it are never taken for motion; a dead host's board is left at
    zero torque.

    Parameters
    ----------
    driver : hapsim.drivers.haply2.Haply2DIY
    scene : hapsim.scene.SceneND
        A 2-D pantograph scene (its operating point's joints [rad]).

    Returns
    -------
    (bytes, None)
        80 bytes and no value index.
    """
    return driver.arm_bytes([math.degrees(v) for v in scene.device.joints]), None
