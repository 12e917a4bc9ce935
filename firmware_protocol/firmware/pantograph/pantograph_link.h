/*
 * pantograph_link.h -- what the two boards of the Hapkit pantograph share: the TWI
 * (I2C) exchange between the leader and the follower, and the calibration block the
 * leader reads from its EEPROM. Included by the firmware (avr-gcc: `float` is 32-bit,
 * unsuffixed literals are `double` = float) and by the emulated two-board plant in
 * ../sim (host C: the same layout, written into the leader's EEPROM image).
 *
 * The build: two Hapkit 3 boards (ATmega328P, 16 MHz), each driving one proximal link of
 * a planar five-bar linkage through its capstan and sector (hapkit_geometry.h: one count
 * of the magnetoresistive sensor turns the sector by pi / 921 * rp / rs rad; full PWM
 * duty is T_max * rs / rp of joint torque). The leader talks to the host over its UART
 * (the framed protocol, n_axes = 2: STATE carries the joint angles [rad], FORCE the joint
 * torques [N m]; the host does the kinematics) and is the TWI master; the follower is a
 * TWI slave at PG_FOLLOWER_ADDR that also answers the general call.
 *
 * One tick on the bus (the leader's Timer1 starts it; docs/pantograph.md draws it):
 *
 *   1. SYNC: a general call (SLA+W to address 0) and STOP, no data. The leader's
 *      "SLA+W acknowledged" interrupt (TWSR 0x18) and the follower's "general call
 *      received" interrupt (0x70) come at the end of the same acknowledge bit: both apply
 *      the drive they hold (the zero-order hold of the torque) and start their ADC there,
 *      so the two joints are sampled and driven at one instant.
 *   2. READ: when its conversion is done the leader reads PG_READ_BYTES from the follower:
 *      the follower's raw 10-bit sample (its two high bits in the second byte, with the
 *      flags above them) and a check byte.
 *   3. DRIVE: once the host's FORCE for this tick is in, the leader writes the follower's
 *      drive for the next tick (PG_DRIVE_BYTES: PWM steps 0..256, direction, check); the
 *      follower holds it and applies it at the next SYNC. The leader applies its own drive
 *      at that SYNC only when this write was acknowledged to its last byte, so the two
 *      joints always change torque at the same tick.
 * A NACK anywhere (no follower, a follower not listening) ends the transaction with STOP;
 * the leader stops driving (zero torque on both joints), latches FAULT SENSOR (detail:
 * PG_NACK_* | TWSR << 8) and disarms.
 */
#ifndef PANTOGRAPH_LINK_H
#define PANTOGRAPH_LINK_H

#define PG_FOLLOWER_ADDR 0x21      /* 7-bit TWI address of the follower */
#define PG_READ_BYTES 3            /* raw lo, raw hi | flags << 2, check */
#define PG_DRIVE_BYTES 3           /* n lo, (n >> 8) | dir << 1, check */
#define PG_CHECK_SEED 0xA5         /* check byte = seed ^ the other bytes (XOR) */
#define PG_FLAG_FRESH 0x04         /* (in the second byte) a conversion since the last READ */
#define PG_FLAG_BAD_DRIVE 0x08     /* (in the second byte) a DRIVE failed its check since */

/* The follower zeroes its motor when no SYNC came for this long [ms] (the leader or the
 * bus gone: nobody else can stop it) */
#define PG_FOLLOWER_WATCHDOG_MS 20UL

/* FAULT SENSOR details (low byte; TWSR in the next byte) */
#define PG_NACK_SYNC 1
#define PG_NACK_READ 2
#define PG_NACK_DRIVE 3
#define PG_BAD_READ 4              /* a READ failed its check byte */

/* TWI bit rate: SCL = F_CPU / (16 + 2 TWBR) = 400 kHz (fast mode) at 16 MHz. (simavr
 * 1.6 times the bus itself at one bit per microsecond, whatever TWBR says.) */
#define PG_TWBR 12

/* The calibration block at EEPROM address 0 (little-endian, as avr-gcc and x86 store):
 * magic and the joint angles [rad] at which the linkage sits when the leader takes its
 * zero (its first samples: the home), checked by hp_crc16 over the bytes before `crc`.
 * Without a valid block the firmware uses PG_DEFAULT_Q1/Q2. (The five-bar's lengths are
 * the host's: the leader reports joint angles and takes joint torques.) */
#define PG_CALIB_MAGIC 0x31434750UL /* "PGC1" */
typedef struct {
    uint32_t magic;
    float home_q1, home_q2;    /* joint angles at the zero [rad] */
    uint16_t crc;
} pg_calib_t;

/* Default home: joints (130, 50) deg, the operating point of configs/pantograph_*.yaml. */
#define PG_DEFAULT_Q1 2.26892802759263   /* 130 deg */
#define PG_DEFAULT_Q2 0.872664625997165  /* 50 deg */

#endif /* PANTOGRAPH_LINK_H */
