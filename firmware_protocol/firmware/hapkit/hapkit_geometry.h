/*
 * hapkit_geometry.h -- the Hapkit 3 mechanism and sensor, in one place.
 *
 * Shared by the firmware (which turns ADC counts into handle position and handle force into
 * PWM duty) and by the emulated board in ../sim (which turns the PWM back into force and the
 * handle position into the sensor voltage), so that both sides agree on the device and only
 * the board integrates physics.
 *
 * The constants are plain (unsuffixed) literals: `double` on the host, `float` under
 * avr-gcc, whose `double` is 32-bit.
 *
 * Mechanism (Stanford Hapkit 3, as published for the board): the motor turns a capstan
 * (pulley) of radius HK_CAPSTAN_RADIUS_M, which drives by a cable a sector of radius
 * HK_SECTOR_RADIUS_M; the handle of length HK_HANDLE_LENGTH_M is fixed to the sector. So
 *
 *     sector angle   theta_s = theta_m * rp / rs              [rad]
 *     handle x       x       = rh * theta_s                   [m]
 *     handle force   F       = T_m * (rs / rp) / rh           [N]  (motor torque T_m [N m])
 *
 * Sensor: a magnetoresistive angle sensor (NXP KMA210) facing a magnet on the motor shaft:
 * its output is periodic in the shaft angle with period pi (half a turn), ratiometric to
 * the 5 V supply; here it spans HK_SENSOR_LO_COUNTS .. HK_SENSOR_LO_COUNTS +
 * HK_SENSOR_SPAN_COUNTS of the 10-bit ADC (5 % .. 95 % of 1023) linearly over each half
 * turn. The firmware counts the flips (the jumps of about one span between two samples)
 * to unwrap the shaft angle over many half turns.
 *
 * Actuator: PWM duty n / HK_PWM_STEPS (n = 0..256: OC0B off, then OCR0B = n - 1 in 8-bit
 * fast PWM) of a motor giving HK_MOTOR_TORQUE_MAX_NM at full duty, sign by the direction
 * pin (D8 high: positive force). The board models the torque as linear in the duty.
 */
#ifndef HAPKIT_GEOMETRY_H
#define HAPKIT_GEOMETRY_H

#define HK_HANDLE_LENGTH_M 0.090      /* rh: handle pivot to the hand [m] */
#define HK_SECTOR_RADIUS_M 0.073152   /* rs: sector radius [m] */
#define HK_CAPSTAN_RADIUS_M 0.004191  /* rp: capstan (motor pulley) radius [m] */
#define HK_MOTOR_TORQUE_MAX_NM 0.03   /* motor torque at 100 % duty [N m] */

#define HK_SENSOR_LO_COUNTS 51        /* ADC counts at the start of a half turn */
#define HK_SENSOR_SPAN_COUNTS 921     /* ADC counts per half turn of the motor shaft */
#define HK_SENSOR_PERIOD_RAD 3.14159265358979 /* shaft angle per sensor period [rad] */
#define HK_ADC_VREF_MV 5000           /* AVcc reference [mV] */
#define HK_ADC_MAX 1023               /* 10-bit ADC full scale [counts] */

#define HK_PWM_STEPS 256              /* duty resolution: n / 256, n = 0..256 */

/* Handle position per unwrapped ADC count [m/count]: rh * (rp / rs) * pi / span. */
#define HK_POSITION_SCALE_M (HK_HANDLE_LENGTH_M * HK_CAPSTAN_RADIUS_M / HK_SECTOR_RADIUS_M * \
                             HK_SENSOR_PERIOD_RAD / HK_SENSOR_SPAN_COUNTS)
/* Handle force at full duty [N]: T_max * (rs / rp) / rh. */
#define HK_FORCE_MAX_N (HK_MOTOR_TORQUE_MAX_NM * HK_SECTOR_RADIUS_M / HK_CAPSTAN_RADIUS_M / \
                        HK_HANDLE_LENGTH_M)
/* Handle force per PWM step [N/unit]. */
#define HK_FORCE_SCALE_N (HK_FORCE_MAX_N / HK_PWM_STEPS)

#endif /* HAPKIT_GEOMETRY_H */
