/*
 * pantograph.c -- hapsim protocol version 1 firmware for the Hapkit pantograph: two Hapkit 3
 * boards (ATmega328P, 16 MHz) on one TWI bus, one per proximal link of a five-bar
 * linkage. One source, two roles chosen at compile time (make: pantograph_leader.elf,
 * pantograph_follower.elf): -DPG_LEADER or -DPG_FOLLOWER.
 *
 * Pins (each board, as the Hapkit 3): MR sensor on A2 (ADC2), motor PWM on D5 (Timer0
 * OC0B, 62.5 kHz), direction on D8 (PB0), D13 (PB5) high while the MCU works on a tick
 * (the budget probe the emulated board measures), TWI on A4/A5 (SDA/SCL).
 *
 * The leader (UART to the host, TWI master) speaks the framed protocol with n_axes = 2 as a
 * joint-level device: HELLO (device id "HKG2", position_scale = rad per sensor count,
 * force_scale = N m per PWM step), CONFIG (rates that divide 16 MHz, PG_MIN_RATE_HZ ..
 * PG_MAX_RATE_HZ), STATE with the joint angles (q1, q2) [rad], FORCE with the joint
 * torques (tau1, tau2) [N m], PING/PONG, STOP, SENSORS (no extra sensor; the compact
 * frames offered: STATE_COMPACT / FORCE_COMPACT with binary32 angles and torques, what
 * hapsim asks for: at 1 kHz they leave a host 372 us to answer, the full frames none),
 * the watchdog. The host does the kinematics (x = f(q), tau = J(q_n)^T F): in float32 on
 * this 16 MHz AVR the five-bar's forward kinematics and Jacobian took ~20,000 cycles a
 * tick, more than the 16,000 of a 1 kHz period (docs/pantograph.md). Each tick
 * (pantograph_link.h): SYNC on the bus (both joints sampled and driven at one instant),
 * the follower's sample READ, the joint angles unwrapped (flip counting, as the 1-DoF
 * firmware) from the home of the calibration block in EEPROM, STATE; a FORCE answering
 * STATE n is quantised to PWM steps, the follower's sent by DRIVE at the tick's DRIVE
 * slot (100 us before the next tick), both applied at that tick: tick n + 1 (delay d = 1)
 * when the FORCE was decoded before the slot, a tick later when not (a late tick, named
 * by the next STATEs' force_seq: the tick itself never moves).
 *
 * The follower (TWI slave) holds the drive it was sent, applies it and starts its ADC at
 * each SYNC, and hands its raw sample to the READ. It has no clock of its own for the
 * loop: the leader's SYNC is its tick.
 *
 * No malloc, no recursion; each tick's work is bounded (one conversion, the kinematics,
 * one STATE encode, the frames received).
 */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <math.h>
#include <stddef.h>
#include <string.h>

#include "../../c/hproto.h"
#include "../hapkit/hapkit_geometry.h"
#include "../hapkit/hk_shared.h"
#include "pantograph_link.h"

#if defined(PG_LEADER) == defined(PG_FOLLOWER)
#error "build with -DPG_LEADER or -DPG_FOLLOWER"
#endif

/* TWCR bits for "go on": interrupt flag cleared, enabled, interrupt on */
#define TW_GO ((uint8_t)((1 << TWINT) | (1 << TWEN) | (1 << TWIE)))

/* What the tick puts on the PWM: duty n / 256 (0 = off) and the direction. */
typedef struct {
    uint16_t n;
    uint8_t dir;
} drive_t;


static void motor_adc_init(void)
{
    DDRD |= (uint8_t)(1 << PD5);
    PORTD &= (uint8_t)~(1 << PD5);
    DDRB |= (uint8_t)((1 << PB0) | (1 << PB5));
    TCCR0A = (uint8_t)((1 << WGM01) | (1 << WGM00)); /* fast PWM 8-bit, OC0B off */
    TCCR0B = (uint8_t)(1 << CS00);
    OCR0B = 0;
    ADMUX = (uint8_t)((1 << REFS0) | 2u);            /* AVcc, ADC2 */
    DIDR0 = (uint8_t)(1 << ADC2D);
    ADCSRA = (uint8_t)((1 << ADEN) | (1 << ADIE) | (1 << ADPS2) | (1 << ADPS0)); /* clk/32 */
}

/* ================================================================ the follower */
#ifdef PG_FOLLOWER

static volatile drive_t f_hold;          /* applied at the next SYNC */
static volatile uint8_t f_tx[PG_READ_BYTES];
static volatile uint8_t f_rx[PG_DRIVE_BYTES];
static volatile uint8_t f_tx_i, f_rx_i, f_flags;

ISR(TWI_vect)
{
    switch (TWSR & 0xF8u) {
    case 0x70: /* general call: SYNC -- drive and sample now */
        pwm_write(f_hold.n, f_hold.dir);
        ADCSRA |= (uint8_t)(1 << ADSC);
        TCNT1 = 0; /* the leader is there: the watchdog starts again */
        TCNT0 = 0; /* the PWM carrier in the leader's phase (the leader restarts its own
                    * with its tick clock): the same at every tick of every session */
        PORTB |= (uint8_t)(1 << PB5);
        f_rx_i = 0xFFu; /* no data expected */
        break;
    case 0x60: /* own SLA+W: a DRIVE starts */
        f_rx_i = 0;
        break;
    case 0x80: /* a DRIVE byte */
    case 0x90:
        if (f_rx_i < PG_DRIVE_BYTES) {
            f_rx[f_rx_i++] = TWDR;
        }
        break;
    case 0xA0: /* STOP: a whole, checked DRIVE is held for the next SYNC */
        if (f_rx_i == PG_DRIVE_BYTES) {
            uint8_t c = (uint8_t)(PG_CHECK_SEED ^ f_rx[0] ^ f_rx[1]);
            uint16_t n = (uint16_t)(f_rx[0] | ((uint16_t)(f_rx[1] & 1u) << 8));
            if (c == f_rx[2] && n <= HK_PWM_STEPS) {
                f_hold.n = n;
                f_hold.dir = (uint8_t)((f_rx[1] >> 1) & 1u);
            } else {
                f_flags |= PG_FLAG_BAD_DRIVE;
            }
        }
        f_rx_i = 0xFFu;
        PORTB &= (uint8_t)~(1 << PB5);
        break;
    case 0xA8: /* own SLA+R: the READ starts with the first byte */
        f_tx_i = 0;
        /* fall through */
    case 0xB8:
        TWDR = f_tx[f_tx_i < PG_READ_BYTES ? f_tx_i : PG_READ_BYTES - 1u];
        f_tx_i++;
        if (f_tx_i >= PG_READ_BYTES) {
            f_flags &= (uint8_t)~(PG_FLAG_FRESH | PG_FLAG_BAD_DRIVE);
        }
        break;
    default: /* 0xC0, 0xC8: the master took what it wanted; bus errors: recover */
        break;
    }
    TWCR = (uint8_t)(TW_GO | (1 << TWEA));
}

/* The follower's watchdog: no SYNC for PG_FOLLOWER_WATCHDOG_MS (the leader or the bus
 * gone): zero torque, held until the next DRIVE says otherwise. */
ISR(TIMER1_COMPA_vect)
{
    f_hold.n = 0;
    f_hold.dir = 0;
    pwm_write(0, 0);
}

ISR(ADC_vect)
{
    uint16_t raw = ADC;
    uint8_t lo = (uint8_t)raw, hi;
    f_flags |= PG_FLAG_FRESH;
    hi = (uint8_t)((raw >> 8) | f_flags);
    f_tx[0] = lo;
    f_tx[1] = hi;
    f_tx[2] = (uint8_t)(PG_CHECK_SEED ^ lo ^ hi);
}

int main(void)
{
    motor_adc_init();
    f_rx_i = 0xFFu;
    f_tx[2] = PG_CHECK_SEED;
    /* Timer1, CTC at clk/64 (4 us a count): the watchdog's compare */
    OCR1A = (uint16_t)(PG_FOLLOWER_WATCHDOG_MS * (F_CPU / 64000UL) - 1UL);
    TCCR1B = (uint8_t)((1 << WGM12) | (1 << CS11) | (1 << CS10));
    TIMSK1 = (uint8_t)(1 << OCIE1A);
    TWAR = (uint8_t)((PG_FOLLOWER_ADDR << 1) | 1u); /* own address, general call on */
    TWCR = (uint8_t)((1 << TWEA) | (1 << TWEN) | (1 << TWIE));
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
    sleep_enable();
    for (;;) {
        sleep_cpu(); /* everything happens in the interrupts */
    }
}

#endif /* PG_FOLLOWER */

/* ================================================================ the leader */
#ifdef PG_LEADER

#include "../hapkit/uart.h"

#define PG_DEVICE_ID 0x32474B48UL  /* "HKG2" little-endian */
#define PG_NATIVE_RATE_HZ 1000UL
#define PG_MIN_RATE_HZ 250UL       /* Timer1 at clk/1: the period fits 16 bits */
#ifndef PG_MAX_RATE_HZ
#define PG_MAX_RATE_HZ 1000UL      /* the cycle budget measured at 1 kHz (docs) */
#endif
/* joint angle per unwrapped count [rad] and joint torque per PWM step [N m] */
#define PG_RAD_PER_COUNT ((float)(HK_SENSOR_PERIOD_RAD / HK_SENSOR_SPAN_COUNTS * \
                                  HK_CAPSTAN_RADIUS_M / HK_SECTOR_RADIUS_M))
#define PG_TAU_MAX_NM ((float)(HK_MOTOR_TORQUE_MAX_NM * HK_SECTOR_RADIUS_M / \
                               HK_CAPSTAN_RADIUS_M))
#define PG_STEPS_PER_NM ((float)HK_PWM_STEPS / PG_TAU_MAX_NM)

enum { OP_IDLE = 0, OP_SYNC, OP_READ, OP_DRIVE };

/* The DRIVE slot: a FORCE's DRIVE goes on the bus at Timer1's compare B, this many cycles
 * before the tick (compare A), and ends before it (the longest DRIVE seen on the emulated
 * bus, its address byte to its STOP, was 927-995 cycles in lockstep and 1,239 in real time
 * with a host's bytes pouring in: four bytes of nine bus clocks, the follower's clock
 * stretching and the ISRs' latency; pantograph_board's report, twi.drive_max_cycles). A FORCE decoded before the slot is
 * applied at the next tick; one decoded after it waits for the next slot and is applied a
 * tick later, which its STATE names (force_seq): a known input to the host, never a
 * moved tick (a SYNC waiting behind a DRIVE would sample and drive the joints up to a
 * DRIVE late, a timing the host cannot know). At the slot nothing else is on the critical
 * path: a DRIVE started at once instead, when its FORCE came late, slowed the next
 * tick's STATE or FORCE by 600-1,000 cycles (its bus interrupts), so that FORCE missed
 * its tick in turn: one late tick made every later one late. */
#define PG_DRIVE_SLOT_CYCLES 1600u

/* Both joints' next drive: the follower's DRIVE bytes and the leader's own drive, with
 * what they come from. The follower holds the last DRIVE it received whole and applies it
 * at the next SYNC; the leader takes the same pair once the follower acknowledged its
 * last byte, so both joints always change torque at the same tick. */
typedef struct {
    uint8_t dr[PG_DRIVE_BYTES]; /* the follower's DRIVE */
    drive_t own;                /* the leader's drive */
    uint32_t seq;               /* the FORCE it answers (when `force`) */
    uint8_t force;              /* from a FORCE; else a zeroing (CONFIG, STOP, fault, watchdog) */
    uint8_t clamped;            /* the FORCE's torques were clamped */
    uint8_t watchdog;           /* the watchdog's zeroing: it trips when this is applied */
} pair_t;
#define PG_STATE_PACKET 37u /* type, seq, time, status, force_seq, 2 x f64, crc */
#define PG_FORCE_PACKET 23u /* type, seq, 2 x f64, crc */
#define PG_STATE_COMPACT_PACKET 15u /* type, seq16, status8, lag, 2 x f32, crc */
#define PG_FORCE_COMPACT_PACKET 13u /* type, seq16, 2 x f32, crc */

/* ---------------------------------------------------------------- shared with the ISRs */
static volatile uint8_t g_op;            /* the TWI transaction under way */
static volatile uint8_t g_rd[PG_READ_BYTES], g_rd_i;
static volatile uint8_t g_dr_i;
static volatile uint8_t g_drive_queued;  /* g_queued waits for the bus */
static volatile uint8_t g_drive_now;     /* ... and goes as soon as it fits (a zeroing) */
static volatile uint8_t g_sync_queued;   /* a tick came while the bus was busy */
/* the drives (ISRs and cli sections only): queued, on the bus, acknowledged whole */
static pair_t g_queued, g_fly, g_acked;
static volatile uint8_t g_own_ready;     /* g_acked is to be applied at the next SYNC */
static drive_t g_own_hold;               /* the leader's drive applied (ISRs, cli) */
static volatile uint16_t g_adc_raw;
static volatile uint8_t g_adc_done, g_tick_flag, g_overrun, g_nack;
static volatile uint16_t g_nack_detail;
static volatile uint32_t g_ticks;
static volatile uint8_t g_armed, g_tripped, g_trip_event, g_force_applied, g_clamped_now;
static volatile uint32_t g_force_seq;
static volatile uint32_t g_taken_seq;    /* the newest FORCE taken this session */
static volatile uint8_t g_have_taken;
static volatile uint16_t g_wd_reload, g_wd_left;
static volatile uint32_t g_period_cycles = F_CPU / PG_NATIVE_RATE_HZ;
static volatile uint64_t g_clock_cycles; /* the device clock at the last tick [cycles] */
static volatile uint8_t g_read_queued;   /* a conversion is done, the bus was busy */
static volatile uint8_t g_sampled;       /* a SYNC of this session sampled: its READ counts */

/* ---------------------------------------------------------------- main loop only */
static pg_calib_t g_cal;
static uint8_t g_configured, g_fault_latched, g_rx_error, g_have_zero;
static uint8_t g_compact;                 /* the host enabled the compact frames */
static uint32_t g_bad_frames, g_bad_reported;
static uint16_t g_rx_lost_seen;
static int16_t g_last_raw[2];
static int32_t g_offset[2];
static float g_limit;                     /* CONFIG's limit on each torque [N m] */

static void twi_start(uint8_t op)
{
    g_op = op;
    TWCR = (uint8_t)(TW_GO | (1 << TWSTA));
}

/* A DRIVE started now ends before the next tick (interrupts off: Timer1 counts 0 ..
 * OCR1A in CTC mode; a compare A already flagged is a tick whose SYNC has not gone yet). */
static uint8_t drive_fits(void)
{
    return !(TIFR1 & (uint8_t)(1 << OCF1A)) &&
           (uint16_t)(OCR1A - TCNT1) > (uint16_t)(PG_DRIVE_SLOT_CYCLES - 40u);
}

/* The queued pair goes on the bus (interrupts off, the bus idle). */
static void drive_start(void)
{
    g_fly = g_queued;
    g_drive_queued = 0;
    g_dr_i = 0;
    twi_start(OP_DRIVE);
}

/* The transaction is over: STOP, then whatever waits for the bus. */
static void twi_done(void)
{
    TWCR = (uint8_t)((1 << TWINT) | (1 << TWEN) | (1 << TWIE) | (1 << TWSTO));
    g_op = OP_IDLE;
    if (g_sync_queued) {
        g_sync_queued = 0;
        twi_start(OP_SYNC);
    } else if (g_read_queued) {
        g_read_queued = 0;
        twi_start(OP_READ);
    } else if (g_drive_queued && g_drive_now && drive_fits()) {
        drive_start();
    }
}

static void twi_fail(uint8_t what, uint8_t st)
{
    g_nack = 1;
    g_nack_detail = (uint16_t)(what | ((uint16_t)st << 8));
    g_drive_queued = 0;
    g_read_queued = 0;
    g_own_ready = 0;
    g_armed = 0;
    pwm_write(0, 0);
    twi_done();
}

/* The tick's instant: the leader's drive on its pin and its ADC started (the follower
 * applies the same pair at the same acknowledge bit). */
static void sample_now(void)
{
    uint8_t fresh = 0;
    if (g_own_ready) {
        g_own_ready = 0;
        g_own_hold = g_acked.own;
        if (g_acked.force) {
            fresh = 1;
            g_force_seq = g_acked.seq;
            g_clamped_now = g_acked.clamped;
        } else {
            g_clamped_now = 0; /* a zeroing (CONFIG, STOP, fault, watchdog): no FORCE */
            if (g_acked.watchdog && g_armed && !g_tripped) {
                g_tripped = 1;  /* both joints at zero from this tick on */
                g_trip_event = 1;
            }
        }
    }
    pwm_write(g_armed ? g_own_hold.n : 0u, g_own_hold.dir);
    ADCSRA |= (uint8_t)(1 << ADSC);
    g_sampled = 1;
    if (fresh) {
        g_force_applied = 1;
        g_wd_left = g_wd_reload;
        g_tripped = 0;
    } else if (g_armed && g_wd_left) {
        g_wd_left--; /* at 0 the main loop sends the watchdog's zeroing */
    }
}

ISR(TWI_vect)
{
    uint8_t st = TWSR & 0xF8u;
    switch (st) {
    case 0x08: /* START sent */
    case 0x10:
        TWDR = g_op == OP_SYNC ? 0u
               : (uint8_t)((PG_FOLLOWER_ADDR << 1) | (g_op == OP_READ ? 1u : 0u));
        TWCR = TW_GO;
        return;
    case 0x18: /* SLA+W acknowledged */
        if (g_op == OP_SYNC) {
            sample_now(); /* the same acknowledge bit as the follower's 0x70 */
            twi_done();
            return;
        }
        /* fall through - the DRIVE's first byte */
    case 0x28: /* a byte acknowledged (simavr 1.6 reports the address so as well) */
        if (g_op == OP_SYNC) {
            sample_now();
            twi_done();
            return;
        }
        if (g_dr_i < PG_DRIVE_BYTES) {
            TWDR = g_fly.dr[g_dr_i++];
            TWCR = TW_GO;
        } else { /* all acknowledged: the leader's drive goes with the follower's */
            g_acked = g_fly;
            g_own_ready = 1;
            twi_done();
        }
        return;
    case 0x20: /* SLA+W not acknowledged */
        if (g_op == OP_SYNC) {
            sample_now(); /* the leader keeps its clock; the fault zeroes the drives */
            twi_fail(PG_NACK_SYNC, st);
        } else {
            twi_fail(PG_NACK_DRIVE, st);
        }
        return;
    case 0x30: /* a byte not acknowledged (simavr 1.6: the address too) */
        if (g_op == OP_SYNC) {
            sample_now();
            twi_fail(PG_NACK_SYNC, st);
            return;
        }
        twi_fail(PG_NACK_DRIVE, st);
        return;
    case 0x40: /* SLA+R acknowledged */
        g_rd_i = 0;
        TWCR = (uint8_t)(TW_GO | (1 << TWEA));
        return;
    case 0x50: /* a byte, more wanted */
    case 0x58: /* the last byte */
        if (g_rd_i < PG_READ_BYTES) {
            g_rd[g_rd_i++] = TWDR;
        }
        if (st == 0x58 || g_rd_i >= PG_READ_BYTES) {
            twi_done();
            /* a READ of a sample taken before a CONFIG restarted the ticks is dropped
             * (with its conversion: not an overrun of the new session's first tick) */
            g_tick_flag = g_sampled;
            if (!g_sampled) {
                g_adc_done = 0;
            }
            g_sampled = 0;
        } else {
            TWCR = (uint8_t)(g_rd_i + 1u < PG_READ_BYTES ? TW_GO | (1 << TWEA) : TW_GO);
        }
        return;
    case 0x48: /* SLA+R not acknowledged */
        twi_fail(PG_NACK_READ, st);
        g_tick_flag = 1;
        return;
    default: /* arbitration lost, bus error */
        twi_fail(PG_NACK_SYNC, st);
        return;
    }
}

ISR(TIMER1_COMPA_vect)
{
    PORTB |= (uint8_t)(1 << PB5); /* budget probe: busy */
    if (g_tick_flag | g_adc_done) {
        g_overrun = 1;
    }
    if (g_op == OP_IDLE) {
        twi_start(OP_SYNC);
    } else {
        g_sync_queued = 1; /* a DRIVE still on the bus: the tick waits for it */
        g_overrun = 1;
    }
    g_ticks++;
    g_clock_cycles += g_period_cycles; /* a 64-bit add here, no multiply in now_us */
}

/* The DRIVE slot (PG_DRIVE_SLOT_CYCLES before the tick): the pair queued goes now. */
ISR(TIMER1_COMPB_vect)
{
    if (g_drive_queued && g_op == OP_IDLE && !g_sync_queued) {
        drive_start();
    }
}

/* The tick's conversion is done: read the follower's sample of the same instant. */
ISR(ADC_vect)
{
    g_adc_raw = ADC;
    g_adc_done = 1;
    if (g_op == OP_IDLE) {
        twi_start(OP_READ);
    } else {
        g_read_queued = 1; /* after the transaction on the bus (a DRIVE) */
    }
}

/* ---------------------------------------------------------------- sending */

static void send(const hp_msg_t *m)
{
    uint8_t frame[HP_MAX_FRAME];
    size_t n = hp_encode(m, frame, sizeof frame);
    if (n) {
        (void)uart_put(frame, n);
    }
}

static void send_fault(uint16_t code, uint32_t detail)
{
    hp_msg_t m;
    m.type = HP_MSG_FAULT;
    m.u.fault.code = code;
    m.u.fault.detail = detail;
    send(&m);
}

static void send_hello(void)
{
    hp_msg_t m;
    m.type = HP_MSG_LINK;
    m.u.link.baud = HK_BAUD;
    m.u.link.bits_per_byte = HK_BITS_PER_BYTE;
    send(&m);
    m.type = HP_MSG_HELLO;
    m.u.hello.protocol_version = HP_PROTOCOL_VERSION;
    m.u.hello.n_axes = 2;
    m.u.hello.device_id = PG_DEVICE_ID;
    /* joint angle per count [rad] and joint torque per PWM step [N m]: the positions and
     * forces on the wire are Cartesian, these are the joints' resolution */
    m.u.hello.position_scale = f64_of_float(PG_RAD_PER_COUNT);
    m.u.hello.force_scale = f64_of_float(1.0f / PG_STEPS_PER_NM);
    m.u.hello.force_limit = f64_of_float(1e30f);
    m.u.hello.native_rate_hz = f64_of_float((float)PG_NATIVE_RATE_HZ);
    send(&m);
}

#if F_CPU != 16000000UL
#error "now_us() assumes 16 MHz"
#endif

/* The device clock at the last tick [us] (the STATE's time; a PONG's within a period). */
static uint64_t now_us(void)
{
    uint64_t c;
    uint8_t s = SREG;
    cli();
    c = g_clock_cycles;
    SREG = s;
    return c >> 4; /* 16 cycles per microsecond at 16 MHz */
}

static void timer1_start(uint32_t period_cycles)
{
    TCCR1B = (uint8_t)(1 << WGM12);
    TCNT1 = 0;
    /* the PWM carrier restarts with the tick clock: its phase at every tick is the same
     * in every session, whatever cycle the CONFIG came at (as the 1-DoF firmware: simavr
     * wakes a sleeping core on its timers' events) */
    TCNT0 = 0;
    TIFR1 = (uint8_t)(1 << OCF1A);
    OCR1A = (uint16_t)(period_cycles - 1u);
    OCR1B = (uint16_t)(period_cycles - 1u - PG_DRIVE_SLOT_CYCLES);
    TIFR1 = (uint8_t)(1 << OCF1B);
    TCCR1B = (uint8_t)((1 << WGM12) | (1 << CS10));
    TIMSK1 = (uint8_t)((1 << OCIE1A) | (1 << OCIE1B));
}

static void load_calibration(void)
{
    eeprom_read_block(&g_cal, (const void *)0, sizeof g_cal);
    if (g_cal.magic != PG_CALIB_MAGIC ||
        hp_crc16(0xFFFFu, (const uint8_t *)&g_cal, offsetof(pg_calib_t, crc)) != g_cal.crc ||
        !isfinite(g_cal.home_q1) || !isfinite(g_cal.home_q2)) {
        g_cal.home_q1 = (float)PG_DEFAULT_Q1;
        g_cal.home_q2 = (float)PG_DEFAULT_Q2;
    }
}

/* ---------------------------------------------------------------- protocol */

static void zero_now(void)
{
    uint8_t s = SREG;
    cli();
    g_own_ready = 0;
    g_own_hold.n = 0;
    g_own_hold.dir = 0;
    pwm_write(0, 0);
    g_clamped_now = 0;
    SREG = s;
}

static void zero_drives(uint8_t watchdog);

static void latch_fault(uint16_t code, uint32_t detail)
{
    g_armed = 0;
    g_fault_latched = 1;
    zero_now();
    zero_drives(0);
    send_fault(code, detail);
}

/* Both joints' next drive (p.dr filled here from `follower`), queued for the next DRIVE
 * slot (a FORCE's), or `now` (a zeroing: on the bus at once when it ends before the next
 * tick), replacing a pair queued before (the bus is never given a DRIVE of two pairs: the
 * pair on it is g_fly's copy). */
static void queue_pair(pair_t *p, drive_t follower, uint8_t now)
{
    uint8_t b0 = (uint8_t)follower.n;
    uint8_t b1 = (uint8_t)(((follower.n >> 8) & 1u) | (uint8_t)(follower.dir << 1));
    uint8_t s = SREG;
    p->dr[0] = b0;
    p->dr[1] = b1;
    p->dr[2] = (uint8_t)(PG_CHECK_SEED ^ b0 ^ b1);
    cli();
    g_queued = *p;
    g_drive_queued = 1;
    g_drive_now = now;
    if (now && g_op == OP_IDLE && !g_sync_queued && drive_fits()) {
        drive_start();
    }
    SREG = s;
}

/* Both joints to zero torque at the next tick the DRIVE makes (not a FORCE applied);
 * `watchdog`: the watchdog's zeroing (it trips at the tick that applies it). */
static void zero_drives(uint8_t watchdog)
{
    pair_t p;
    drive_t z = {0, 0};
    memset(&p, 0, sizeof p);
    p.watchdog = watchdog;
    queue_pair(&p, z, !watchdog); /* the watchdog's waits for the slot, as a FORCE's */
}

static void on_config(const hp_config_t *c)
{
    uint32_t rate = 0, period;
    uint8_t ok = f64_to_u32_exact(c->rate_hz, &rate);
    ok = ok && rate >= PG_MIN_RATE_HZ && rate <= PG_MAX_RATE_HZ && (F_CPU % rate) == 0;
    period = ok ? F_CPU / rate : 0;
    ok = ok && (uint64_t)c->watchdog_us * rate >= 2000000ULL &&
         (uint64_t)c->watchdog_us * rate / 1000000ULL <= 65535ULL;
    ok = ok && f64_is_finite(c->force_limit) && !(c->force_limit.hi >> 31);
    if (!ok) {
        latch_fault(HP_FAULT_BAD_CONFIG, 0);
        return;
    }
    /* the frames sent so far leave first (a disarmed STATE takes up to 3,120 cycles): the
     * session's STATE 0 is never queued behind them, late for its FORCE */
    while (UCSR0B & (uint8_t)(1 << UDRIE0)) {
    }
    g_limit = float_of_f64(c->force_limit);
    cli();
    g_drive_queued = 0;
    g_period_cycles = period;
    g_wd_reload = (uint16_t)((uint64_t)c->watchdog_us * rate / 1000000ULL - 1u);
    g_wd_left = g_wd_reload;
    g_own_ready = 0;
    g_own_hold.n = 0;
    g_own_hold.dir = 0;
    pwm_write(0, 0);
    g_clamped_now = 0;
    g_tripped = 0;
    g_trip_event = 0;
    g_force_seq = 0;
    g_force_applied = 0;
    g_have_taken = 0;
    g_ticks = 0;
    g_tick_flag = 0;
    g_adc_done = 0;
    g_sampled = 0;
    g_overrun = 0;
    g_nack = 0;
    g_armed = 1;
    timer1_start(period);
    sei();
    /* the follower starts from zero torque: the DRIVE goes now, at the new tick clock's
     * start (queued before the clock restarted, near the old clock's tick, it waited for
     * the session's first slot: the hand, which lets go at the first SYNC after that
     * DRIVE, let go a tick later in some runs than in others) */
    zero_drives(0);
    g_configured = 1;
    g_fault_latched = 0;
}

/* Joint torque tau [N m] as PWM steps and direction; `clamped` set at full duty. */
static drive_t to_drive(float tau, uint8_t *clamped)
{
    drive_t d;
    float a = fabsf(tau) * PG_STEPS_PER_NM;
    if (a >= (float)HK_PWM_STEPS) {
        d.n = HK_PWM_STEPS;
        *clamped = 1;
    } else {
        d.n = (uint16_t)(a + 0.5f);
    }
    d.dir = tau > 0.0f;
    return d;
}

/* The joint torques t1, t2 [N m] (binary32; `finite`: neither is infinite or NaN) of a
 * FORCE answering STATE `seq`. */
static void take_torques(uint32_t seq, float t1, float t2, uint8_t finite)
{
    uint8_t clamped = 0;
    drive_t d2;
    pair_t p;
    if (!g_armed) {
        return;
    }
    if (g_have_taken && (int32_t)(seq - g_taken_seq) <= 0) {
        return; /* not newer than a FORCE taken: a duplicate or a stale one */
    }
    if (!finite) {
        latch_fault(HP_FAULT_NON_FINITE_FORCE, 0);
        return;
    }
    if (fabsf(t1) > g_limit) {
        t1 = t1 > 0 ? g_limit : -g_limit;
        clamped = 1;
    }
    if (fabsf(t2) > g_limit) {
        t2 = t2 > 0 ? g_limit : -g_limit;
        clamped = 1;
    }
    /* both drives computed before the pair is queued: computed after it (the follower's
     * DRIVE on the bus sooner), the leader's was put into the pair wherever it had got to,
     * and in a burst of FORCEs (a host catching up: the receive interrupts take half the
     * CPU) the slot's DRIVE was acknowledged and applied before it: a tick with the
     * leader's joint at zero torque, which no STATE names */
    d2 = to_drive(t2, &clamped);
    memset(&p, 0, sizeof p);
    p.own = to_drive(t1, &clamped);
    p.seq = seq;
    p.force = 1;
    p.clamped = clamped;
    g_taken_seq = seq;
    g_have_taken = 1;
    queue_pair(&p, d2, 0);
}

/* A FORCE's binary64 torques: rounded to binary32 (a non-finite one stays non-finite). */
static void take_torques_b64(uint32_t seq, hp_b64_t b1, hp_b64_t b2)
{
    take_torques(seq, float_of_f64(b1), float_of_f64(b2),
                 f64_is_finite(b1) && f64_is_finite(b2));
}

static void on_force(const hp_force_t *f)
{
    if (f->n_axes != 2) {
        send_fault(HP_FAULT_AXES_MISMATCH, f->n_axes);
        return;
    }
    take_torques_b64(f->seq, f->force[0], f->force[1]);
}

/* FORCE_COMPACT: the 16-bit seq restored from the tick counter (the FORCE answers a STATE
 * already sent: hp_compact_seq), the binary32 torques used as they are. */
static void force_compact(uint16_t seq16, uint32_t b1, uint32_t b2)
{
    uint32_t now;
    float t1, t2;
    uint8_t s = SREG;
    cli();
    now = g_ticks - 1u; /* the seq of the last tick's STATE */
    SREG = s;
    memcpy(&t1, &b1, sizeof t1);
    memcpy(&t2, &b2, sizeof t2);
    take_torques(hp_compact_seq(now, seq16), t1, t2,
                 (b1 & 0x7F800000UL) != 0x7F800000UL && (b2 & 0x7F800000UL) != 0x7F800000UL);
}

static void on_message(const hp_msg_t *m)
{
    hp_msg_t r;
    switch (m->type) {
    case HP_MSG_HELLO_REQUEST:
        send_hello();
        if (m->u.hello_request.protocol_version != HP_PROTOCOL_VERSION) {
            latch_fault(HP_FAULT_VERSION_MISMATCH, m->u.hello_request.protocol_version);
        }
        break;
    case HP_MSG_CONFIG:
        on_config(&m->u.config);
        break;
    case HP_MSG_FORCE:
        on_force(&m->u.force);
        break;
    case HP_MSG_FORCE_COMPACT:
        if (m->u.force_compact.n_axes != 2) {
            send_fault(HP_FAULT_AXES_MISMATCH, m->u.force_compact.n_axes);
        } else {
            force_compact(m->u.force_compact.seq, m->u.force_compact.force[0],
                          m->u.force_compact.force[1]);
        }
        break;
    case HP_MSG_PING:
        r.type = HP_MSG_PONG;
        r.u.pong.nonce = m->u.ping.nonce;
        r.u.pong.host_time_us = m->u.ping.host_time_us;
        r.u.pong.device_time_us = now_us();
        send(&r);
        break;
    case HP_MSG_STOP:
        g_armed = 0;
        zero_now();
        zero_drives(0);
        break;
    case HP_MSG_SENSORS_REQUEST:
        /* no extra sensor; the compact frames (PROTOCOL.md section 4): with the full
         * STATE and FORCE (39 + 25 bytes on the wire, 3,200 cycles of codec) the FORCE
         * reaches the DRIVE slot of a 1 kHz tick with no time to spare for a host; the
         * compact ones (17 + 15 bytes) leave it ~4,000 cycles (docs/pantograph.md) */
        r.type = HP_MSG_SENSORS;
        r.u.sensors.offered = HP_FEATURE_COMPACT;
        r.u.sensors.enabled = m->u.sensors_request.sensors & HP_FEATURE_COMPACT;
        g_compact = r.u.sensors.enabled != 0;
        send(&r);
        break;
    default:
        break;
    }
}

static void take_frame(void)
{
    static uint8_t pk[HP_MAX_PACKET];
    hp_msg_t m;
    uint8_t len = uart_packet(pk);
    int r;
    if (!len) {
        return;
    }
    if (len == PG_FORCE_PACKET && pk[0] == HP_MSG_FORCE) {
        /* the one frame of every tick, 2 axes: checked and taken here (hp_decode_packet's
         * result for it, without its dispatch; little-endian, as the wire) */
        if (hp_crc16(0xFFFFu, pk, PG_FORCE_PACKET) == 0) {
            uint32_t seq;
            hp_b64_t b1, b2;
            memcpy(&seq, &pk[1], sizeof seq);
            memcpy(&b1, &pk[5], sizeof b1);
            memcpy(&b2, &pk[13], sizeof b2);
            take_torques_b64(seq, b1, b2);
        } else {
            g_bad_frames++;
            g_rx_error = 1;
        }
        return;
    }
    if (len == PG_FORCE_COMPACT_PACKET && pk[0] == HP_MSG_FORCE_COMPACT) {
        /* the one frame of every tick in a compact session, 2 axes: checked and taken
         * here (hp_decode_packet's result for it, without its dispatch) */
        if (hp_crc16(0xFFFFu, pk, PG_FORCE_COMPACT_PACKET) == 0) {
            uint32_t b1, b2;
            memcpy(&b1, &pk[3], sizeof b1); /* little-endian, as the wire */
            memcpy(&b2, &pk[7], sizeof b2);
            force_compact((uint16_t)(((uint16_t)pk[2] << 8) | pk[1]), b1, b2);
        } else {
            g_bad_frames++;
            g_rx_error = 1;
        }
        return;
    }
    r = len == UART_OVERLONG ? HP_ERR_OVERLONG
        : len == UART_BAD_COBS ? HP_ERR_BAD_COBS : hp_decode_packet(pk, len, &m);
    if (r == HP_OK) {
        on_message(&m);
    } else {
        g_bad_frames++;
        g_rx_error = 1;
    }
}

/* Unwrapped counts of joint i from its raw sample (flip counting; zero at the first). */
static int32_t unwrap(uint8_t i, uint16_t raw)
{
    int16_t d;
    if (!g_have_zero) {
        g_last_raw[i] = (int16_t)raw;
        g_offset[i] = -(int32_t)raw;
    }
    d = (int16_t)((int16_t)raw - g_last_raw[i]);
    if (d > (int16_t)(HK_SENSOR_SPAN_COUNTS / 2)) {
        g_offset[i] -= (int32_t)HK_SENSOR_SPAN_COUNTS;
    } else if (d < -(int16_t)(HK_SENSOR_SPAN_COUNTS / 2)) {
        g_offset[i] += (int32_t)HK_SENSOR_SPAN_COUNTS;
    }
    g_last_raw[i] = (int16_t)raw;
    return (int32_t)raw + g_offset[i];
}

static void serve_tick(void)
{
    uint16_t status = 0, lost, raw0, raw1;
    uint32_t seq, fseq;
    uint8_t s, rd[PG_READ_BYTES], nack, ok_read;
    float q1, q2;
    s = SREG;
    cli();
    raw0 = g_adc_raw;
    memcpy(rd, (const void *)g_rd, sizeof rd);
    g_tick_flag = 0;
    g_adc_done = 0;
    nack = g_nack;
    seq = g_ticks - 1u;
    fseq = g_force_seq;
    if (g_armed) {
        status |= HP_STATUS_ARMED;
    }
    if (g_tripped) {
        status |= HP_STATUS_WATCHDOG_TRIPPED;
    }
    if (g_clamped_now) {
        status |= HP_STATUS_FORCE_CLAMPED;
    }
    if (g_force_applied) {
        status |= HP_STATUS_FORCE_APPLIED;
    }
    if (g_overrun) {
        status |= HP_STATUS_OVERRUN;
        g_overrun = 0;
    }
    SREG = s;
    ok_read = !nack && (uint8_t)(PG_CHECK_SEED ^ rd[0] ^ rd[1]) == rd[2] &&
              (rd[1] & PG_FLAG_FRESH);
    if (nack) {
        g_nack = 0;
        if (!g_fault_latched) {
            latch_fault(HP_FAULT_SENSOR, g_nack_detail);
        }
        return;
    }
    if (!ok_read) {
        if (!g_fault_latched) {
            latch_fault(HP_FAULT_SENSOR, PG_BAD_READ);
        }
        return;
    }
    raw1 = (uint16_t)(rd[0] | ((uint16_t)(rd[1] & 3u) << 8));
    q1 = g_cal.home_q1 + (float)unwrap(0, raw0) * PG_RAD_PER_COUNT;
    q2 = g_cal.home_q2 + (float)unwrap(1, raw1) * PG_RAD_PER_COUNT;
    g_have_zero = 1;
    if (g_fault_latched) {
        status |= HP_STATUS_FAULT;
    }
    if (g_configured) {
        status |= HP_STATUS_CONFIGURED;
    }
    lost = uart_rx_lost();
    if (lost != g_rx_lost_seen) {
        g_rx_lost_seen = lost;
        g_rx_error = 1;
    }
    if (g_rx_error) {
        status |= HP_STATUS_RX_ERROR;
    }
    if (g_compact) {
        /* STATE_COMPACT: seq and status cut to their low bits, the lag saturated at 255
         * (0 before any FORCE), the binary32 angles as they are (hp_encode's bytes) */
        uint32_t lag = seq - fseq;
        uint8_t pk[PG_STATE_COMPACT_PACKET];
        uint16_t crc;
        pk[0] = HP_MSG_STATE_COMPACT;
        pk[1] = (uint8_t)seq;
        pk[2] = (uint8_t)(seq >> 8);
        pk[3] = (uint8_t)status;
        pk[4] = !(status & HP_STATUS_FORCE_APPLIED) ? 0u
                : lag > HP_COMPACT_LAG_MAX ? (uint8_t)HP_COMPACT_LAG_MAX : (uint8_t)lag;
        memcpy(&pk[5], &q1, sizeof q1); /* little-endian, as the wire */
        memcpy(&pk[9], &q2, sizeof q2);
        crc = hp_crc16(0xFFFFu, pk, PG_STATE_COMPACT_PACKET - 2u);
        pk[PG_STATE_COMPACT_PACKET - 2u] = (uint8_t)(crc >> 8);
        pk[PG_STATE_COMPACT_PACKET - 1u] = (uint8_t)crc;
        (void)uart_put_packet(pk, sizeof pk); /* a full ring drops it (a gap) */
    } else {
        /* STATE packed here (hp_encode's bytes: the golden vectors check hp_encode, the
         * closed-loop tests these), COBS-encoded straight into the transmit ring */
        uint8_t pk[PG_STATE_PACKET];
        uint64_t t = now_us();
        hp_b64_t b1 = f64_of_float(q1), b2 = f64_of_float(q2);
        uint16_t crc;
        pk[0] = HP_MSG_STATE;
        memcpy(&pk[1], &seq, 4);
        memcpy(&pk[5], &t, 8);
        memcpy(&pk[13], &status, 2);
        memcpy(&pk[15], &fseq, 4);
        memcpy(&pk[19], &b1, 8);
        memcpy(&pk[27], &b2, 8);
        crc = hp_crc16(0xFFFFu, pk, PG_STATE_PACKET - 2u);
        pk[PG_STATE_PACKET - 2u] = (uint8_t)(crc >> 8);
        pk[PG_STATE_PACKET - 1u] = (uint8_t)crc;
        (void)uart_put_packet(pk, sizeof pk); /* a full ring drops it (a gap) */
    }
    if (g_trip_event) {
        g_trip_event = 0; /* both joints are at zero since the tick (sample_now) */
        send_fault(HP_FAULT_WATCHDOG, 0);
    }
    {
        /* the watchdog ran out (no FORCE applied for its periods): both joints to zero at
         * once, by a DRIVE like a FORCE's, so that it trips at the tick both change; a
         * FORCE taken meanwhile replaces it (rules 2-3 of PROTOCOL.md section 5) */
        uint8_t pending;
        s = SREG;
        cli();
        pending = g_drive_queued || g_op == OP_DRIVE || g_own_ready;
        SREG = s;
        if (g_armed && !g_tripped && g_wd_left == 0 && !pending) {
            zero_drives(1);
        }
    }
    if (g_bad_frames != g_bad_reported) {
        g_bad_reported = g_bad_frames;
        send_fault(HP_FAULT_RX_ERRORS, g_bad_frames);
    }
    g_rx_error = 0;
}

int main(void)
{
    const uint8_t zero = 0;
    load_calibration();
    motor_adc_init();
    uart_init();
    TWBR = PG_TWBR;
    TWSR = 0; /* prescaler 1 */
    TWCR = (uint8_t)((1 << TWEN) | (1 << TWIE));
    timer1_start(g_period_cycles); /* native rate, disarmed: STATE for the host to watch */
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
    (void)uart_put(&zero, 1);
    send_hello();
    sleep_enable();
    for (;;) {
        cli();
        if (g_tick_flag | uart_frame_ready()) {
            sei();
            if (uart_frame_ready()) {
                take_frame();
            }
            if (g_tick_flag) {
                serve_tick();
            }
            continue;
        }
        if (g_op == OP_IDLE) {
            PORTB &= (uint8_t)~(1 << PB5); /* budget probe: idle */
        }
        sei();
        sleep_cpu();
        /* one instruction before the loop's cli: simavr 1.6 runs the instruction after a
         * SLEEP that found an interrupt pending before it serves that interrupt (the chip
         * serves it first); with the loop's cli right after SLEEP (as the compiler laid it
         * out once) the TWI interrupt was never served and the bus stopped at its START */
        __asm__ __volatile__("nop");
    }
}

#endif /* PG_LEADER */
