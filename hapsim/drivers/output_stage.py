"""What a board's firmware makes of the force a command carries before its motor gets it:
its output stage, read from the firmware line by line, in the firmware's own arithmetic.

Two boards quantise the force on its way to the motor, and neither says so in a reply:

- **The Hapkit WHC2017 sketch** (haphub/WHC2017 ef6028f,
  ``hFirmware/Hapkit_Arduino_Control/Hapkit_arduino/Hapkit_Kinematics_Simulation.h``, cited
  ``sim.h:line``): ``Tp = rp/rs * rh * force`` (sim.h:191, the constants at sim.h:38-40,
  ``float``: binary32 on the AVR), the direction pin from ``force > 0`` (sim.h:211-215),
  ``duty = sqrt(abs(Tp)/0.0183)`` (sim.h:218; the AVR's ``double`` is binary32, the
  Arduino core's ``abs`` a macro that keeps the float), clamped to [0, 1] (sim.h:221-225),
  ``output = (int)(duty * 255)`` (sim.h:227, truncated) and ``analogWrite`` of it
  (sim.h:228): 256 levels on a square-root curve. The force the motor then makes is the
  sketch's own motor model inverted, ``0.0183 (n / 255)^2`` N m at the motor pulley,
  ``/ (rp / rs rh)`` at the handle: level ``n`` applies ``4.26 (n / 255)^2`` N, so a force
  is cut to the level below it, by up to ``2 / n`` of itself (1.2 % at 0.5 N, n = 87).
- **The Haply M3, firmware V1.5** (HaplyHaptics/Haply-Arduino-Firmware-Versions,
  ``Haply_M3_Firmware_V1_5/Haply_M3_Firmware_V1_5.h``, cited ``.h:line``; randomvibe's
  ``pwm01.h``; arduino/ArduinoCore-sam ``variants/arduino_due_x/variant.h``):
  ``create_torque`` (.h:467-492) takes ``abs(torque)`` (the SAM core's ``abs`` macro,
  ``cores/arduino/wiring_constants.h:73``), clamps it at ``MAX_TORQUE`` 0.123 N m (.h:54,
  485-487) and computes ``duty = PWM_OUTPUT_RESOLUTION * torque / MAX_TORQUE`` (.h:489:
  ``4095 * torque`` in binary32, divided by the ``double`` 0.123 in binary64 on the Due,
  truncated to ``int``); ``pwm_write_duty`` (pwm01.h:110-120) maps the 12 bits that
  ``pwm_set_resolution(12)`` (.h:173) named to the Due's ``PWM_RESOLUTION`` of 8
  (variant.h:229) by ``mapResolution``'s shift of 4 (pwm01.h:58-66), on a channel whose
  period is ``pwm_max_duty_Ncount`` = 255 counts (pwm01.h:37, 99): the motor gets
  ``(duty >> 4) / 255`` of 0.123 N m, 256 levels 0.482 mN m apart: the duty truncated,
  but its top 8 bits taken as a fraction of 255, not of 4095 / 16, so a level lies up
  to one level below the torque or up to about ``15 k / (255 * 4095)`` of 0.123 N m
  above it at level ``k`` (0.45 mN m at the top; 0.04 N m gives 0.040035).

Both are deterministic functions of the command's value: the host knows the force the
motor got for every command it sent, to within the firmware's rounding where a level's
edge falls within a few units in the last place of its binary32 arithmetic (stated as a
half-width). The measurement takes the difference out as a known input at every row
(:func:`hapsim.analysis.measurement.late_accounted`), as the framed Hapkit's rounding
(:func:`hapsim.applied.firmware_force`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SKETCH_RS", "SKETCH_RP", "SKETCH_RH", "SKETCH_MOTOR_K", "SKETCH_LEVELS",
           "sketch_gearing", "sketch_tp", "sketch_output", "sketch_output_from_tp",
           "M3_MAX_TORQUE", "M3_DUTY_MAX", "M3_SHIFT", "M3_PERIOD", "m3_output",
           "SKETCH_EDGE_ULPS", "sketch_board_output"]

#: The sketch's sector radius, motor pulley radius and handle length [m] (sim.h:38-40).
SKETCH_RS, SKETCH_RP, SKETCH_RH = 0.073152, 0.004191, 0.075
#: The motor pulley's torque at duty 1 in the sketch's motor model [N m] (sim.h:218).
SKETCH_MOTOR_K = 0.0183
#: The largest output of ``analogWrite`` (sim.h:227: ``(int)(duty * 255)``).
SKETCH_LEVELS = 255
#: A level's edge within this many units in the last place of ``duty * 255`` is taken as
#: either level: avr-libc's binary32 routines and this host's may round an operation
#: differently by one unit, and ``Tp``, the quotient, the square root and the product are
#: four operations (a generous 8 for the sum of their errors through the square root).
SKETCH_EDGE_ULPS = 8

#: The Haply M3's torque clamp [N m] (.h:54) and its 12-bit duty's top (.h:55).
M3_MAX_TORQUE = 0.123
M3_DUTY_MAX = 4095
#: ``mapResolution``'s shift from the 12 bits written to the Due's 8 (pwm01.h:58-66,
#: variant.h:229), and the channel's period in counts (pwm01.h:37, 99).
M3_SHIFT = 4
M3_PERIOD = 255

_f32 = np.float32


def sketch_gearing() -> float:
    """The sketch's ``rp/rs * rh`` in its binary32 arithmetic (sim.h:191, left to right):
    the handle force's factor to the motor pulley's torque [m].

    Returns
    -------
    float
        The factor [m], a binary32 value.
    """
    return float(_f32(_f32(_f32(SKETCH_RP) / _f32(SKETCH_RS)) * _f32(SKETCH_RH)))


def sketch_tp(force) -> np.ndarray:
    """The motor pulley's torque ``Tp`` the sketch computes for rendered forces (sim.h:191).

    Parameters
    ----------
    force : array_like, shape (n,)
        The sketch's ``force`` [N] (rounded to binary32 here, as the sketch holds it).

    Returns
    -------
    ndarray of float32, shape (n,)
        ``Tp`` [N m], binary32.
    """
    f = np.asarray(force, np.float64).astype(_f32)
    with np.errstate(over="ignore", invalid="ignore"):
        return _f32(sketch_gearing()) * f


def sketch_output_from_tp(tp, sign_of=None):
    """The force the Hapkit's motor makes at the handle for the sketch's ``Tp`` values, and
    how far the firmware's rounding leaves it uncertain (module notes; sim.h:206-229).

    Parameters
    ----------
    tp : array_like, shape (n,)
        ``Tp`` [N m] (binary32 values, as the sketch computed or replied them).
    sign_of : array_like, shape (n,), optional
        The rendered ``force`` whose sign sets the direction pin (sim.h:211-215); default
        ``tp``'s own (the same sign: the gearing is positive).

    Returns
    -------
    out : ndarray, shape (n,)
        The force applied [N]: ``sign * 0.0183 (n / 255)^2 / (rp / rs rh)``, the middle of
        the two levels where the level is not certain; an infinite ``tp`` the clamp's
        level 255 (as the firmware's ``duty > 1``), a NaN 0.
    half_width : ndarray, shape (n,)
        Half the difference of the two levels there [N], 0 elsewhere.
    level : ndarray of int64, shape (n,)
        The ``analogWrite`` output (the lower of two where uncertain).
    """
    t = np.asarray(tp, np.float64).astype(_f32)
    s = t if sign_of is None else np.asarray(sign_of, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        a = np.abs(t)
        q = a / _f32(SKETCH_MOTOR_K)                            # binary32 quotient
        root = np.sqrt(q)                                       # binary32 root
        duty = np.where(root > _f32(1.0), _f32(1.0), root)
        duty = np.where(duty < _f32(0.0), _f32(0.0), duty)
        v = duty * _f32(SKETCH_LEVELS)                          # binary32 product
        ok = np.isfinite(v)
        v = np.where(ok, v, _f32(0.0))
        n = np.floor(v).astype(np.int64)                        # (int): truncation
        # a level's edge in doubt: the product before the clamp within the ulps of a
        # whole number (past the clamp by more, the duty is 1 exactly: level 255, no doubt)
        raw = np.where(np.isfinite(root), root * _f32(SKETCH_LEVELS), _f32(np.inf))
        m = np.rint(raw)
        edge = (m >= 1) & (m <= SKETCH_LEVELS) & ok & (
            np.abs(raw.astype(np.float64) - m)
            <= SKETCH_EDGE_ULPS * np.spacing(np.maximum(np.minimum(raw, _f32(2.0 ** 20)),
                                                        _f32(1.0))).astype(np.float64))
        m = np.where(edge, m, 0.0)
    lo = np.where(edge, m - 1, n).astype(np.int64)
    hi = np.where(edge, m, n).astype(np.int64)
    scale = SKETCH_MOTOR_K / (SKETCH_RP / SKETCH_RS * SKETCH_RH)
    f_lo = scale * (lo / SKETCH_LEVELS) ** 2
    f_hi = scale * (hi / SKETCH_LEVELS) ** 2
    sign = np.where(s > 0, 1.0, -1.0)
    out = np.where(ok, sign * 0.5 * (f_lo + f_hi), 0.0)
    hw = np.where(ok, 0.5 * (f_hi - f_lo), 0.0)
    return out, hw, lo


def sketch_output(force):
    """The force the Hapkit's motor makes for rendered forces (:func:`sketch_tp`, then
    :func:`sketch_output_from_tp`).

    Parameters
    ----------
    force : array_like, shape (n,)
        The sketch's rendered ``force`` [N] (for the host-force function, the command's
        second float).

    Returns
    -------
    out, half_width : ndarray, shape (n,)
        The force applied [N] and its uncertainty [N] (:func:`sketch_output_from_tp`).
    """
    f = np.asarray(force, np.float64)
    out, hw, _ = sketch_output_from_tp(sketch_tp(f), sign_of=f.astype(_f32))
    return out, hw


def sketch_board_output(force):
    """The force a Hapkit's motor makes for rendered forces, the sketch's arithmetic done
    once in this host's binary32 (sim.h:191, 206-229): the level ``(int)(255 * duty)``
    itself, with no half-width -- what an emulated board applies
    (:class:`hapsim.emulated.hapkit_serial_board.HapkitSerialDevice`); the driver's
    account states the edge's doubt instead (:func:`sketch_output`).

    Parameters
    ----------
    force : array_like, shape (n,)
        The sketch's rendered ``force`` [N].

    Returns
    -------
    ndarray, shape (n,)
        ``sign(force) * 0.0183 (n / 255)^2 / (rp / rs rh)`` [N]; 0 for a non-finite force.
    """
    f = np.asarray(force, np.float64).astype(_f32)
    tp = sketch_tp(f)
    with np.errstate(over="ignore", invalid="ignore"):
        duty = np.sqrt(np.abs(tp) / _f32(SKETCH_MOTOR_K))          # binary32
        duty = np.minimum(duty, _f32(1.0))
        v = duty * _f32(SKETCH_LEVELS)
        ok = np.isfinite(v)
        n = np.floor(np.where(ok, v, _f32(0.0))).astype(np.int64)   # (int): truncation
    scale = SKETCH_MOTOR_K / (SKETCH_RP / SKETCH_RS * SKETCH_RH)
    return np.where(ok, np.where(f > 0, 1.0, -1.0) * scale * (n / SKETCH_LEVELS) ** 2, 0.0)


def m3_output(torque):
    """The torque the Haply M3's motor gets for the torques the writes carry (module notes;
    .h:467-492, pwm01.h:58-66, 110-120).

    Parameters
    ----------
    torque : array_like, shape (n,)
        The write's torque [N m] (rounded to binary32 here, as the firmware reads it).

    Returns
    -------
    out : ndarray, shape (n,)
        ``sign * 0.123 * (duty >> 4) / 255`` [N m] in the host's sign (the direction pin
        from ``torque <= 0``, .h:476-481); 0 for a NaN (its conversion to ``int`` on the
        Due's soft float: 0).
    half_width : ndarray, shape (n,)
        0: the Due's soft-float binary32 product and binary64 quotient round as this host's
        do (IEEE 754, round to nearest), so the duty is exact.
    """
    t = np.asarray(torque, np.float64).astype(_f32)
    with np.errstate(over="ignore", invalid="ignore"):
        a = np.abs(t)
        a = np.where(a.astype(np.float64) > M3_MAX_TORQUE, _f32(M3_MAX_TORQUE), a)
        prod = (_f32(M3_DUTY_MAX) * a).astype(np.float64)        # int * float: binary32
        ok = np.isfinite(prod)
        duty = np.where(ok, np.floor(np.where(ok, prod, 0.0) / M3_MAX_TORQUE), 0.0)
    duty8 = duty.astype(np.int64) >> M3_SHIFT
    sign = np.where(t > 0, 1.0, -1.0)
    out = np.where(ok, sign * M3_MAX_TORQUE * duty8 / M3_PERIOD, 0.0)
    return out, np.zeros(out.shape)
