/*
 * main.c -- hapsim protocol version 1 firmware for the Hapkit 3 board (ATmega328P, 16 MHz).
 *
 * Specification: ../../PROTOCOL.md (device duties, section 5). Pins (Hapkit 3 as
 * published): magnetoresistive sensor on A2 (ADC2), motor PWM on D5 (Timer0, OC0B, 8-bit
 * fast PWM at 62.5 kHz), motor direction on D8 (PB0). D13 (PB5) is high while the MCU
 * works on a tick (a probe for the cycle budget; the emulated board measures it).
 *
 * Timing. Timer1 in CTC mode interrupts at the CONFIG rate (device-clocked). The interrupt
 * (a) applies the force decided for this tick -- the last valid FORCE received, or zero
 * when the watchdog has run out -- to the PWM, which holds it until the next tick (the
 * zero-order hold), and (b) starts the ADC conversion of the sensor, a few cycles after
 * (a) (the model samples and holds at the same instant). The main loop then
 * reads the ADC, unwraps the shaft angle (flip counting), sends STATE, and decodes the
 * frames the UART interrupt cut out of what the host sent (FORCE: converted, clamped and quantised to a PWM step, kept for the next
 * tick). With every FORCE answering STATE n received before tick n + 1, the force is
 * applied at tick n + 1: a loop delay d = 1 (at 1 kHz). Whatever the delay, each STATE
 * reports the FORCE applied (force_seq): at 4 kHz in compact frames it is 2.
 *
 * Compact frames (PROTOCOL.md section 4): offered in SENSORS; once the host enables them,
 * STATE_COMPACT (13 bytes: 16-bit seq, 8-bit status, lag, float32 position) replaces STATE
 * and FORCE_COMPACT (11 bytes: 16-bit seq, float32 force) is taken as FORCE; CONFIG then
 * accepts rates up to 4 kHz (1250 Hz in full frames).
 *
 * Numbers. avr-gcc's double is 32-bit: positions are computed in float32 and sent as the
 * exact binary64 of that float32; forces arrive as binary64 and are rounded to float32
 * (round to nearest, ties to even) in integer code (hp_f32_bits_from_f64_bits). A
 * non-finite force is detected on the binary64 bits.
 *
 * Worst case of every path: no loop waits on the host; the receive and transmit rings are
 * fixed; a tick's work is bounded by one ADC conversion, one STATE encode, at most one
 * FAULT encode and the decoding of the bytes received (each frame at most 127 bytes).
 * No malloc, no recursion.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <string.h>

#include "../../c/hproto.h"
#include "hapkit_geometry.h"
#include "hk_shared.h"
#include "uart.h"

#define HK_DEVICE_ID 0x33544B48UL  /* "HKT3" little-endian */
#define HK_NATIVE_RATE_HZ 1000UL
#define HK_MIN_RATE_HZ 31UL        /* Timer1 period fits 16 bits with prescaler 8 */
#define HK_STATE_FRAME_BYTES 31UL  /* 1-axis STATE on the wire (PROTOCOL.md section 3) */
#define HK_FORCE_FRAME_BYTES 17UL  /* 1-axis FORCE */
/* A rate is carried when the STATE frames use at most 4/5 of the line (the rest for
 * FAULT, PONG and the jitter of the ticks). */
#define HK_LINK_NUM 4UL
#define HK_LINK_DEN 5UL
#define HK_LINK_MAX_RATE_HZ (HK_BAUD * HK_LINK_NUM / (HK_LINK_DEN * HK_BITS_PER_BYTE * \
                                                      HK_STATE_FRAME_BYTES))
/* The MCU's own limit in full frames: a tick with one STATE out and one FORCE in keeps the
 * chip busy about 8.7k cycles (tools/bench_firmware.py on the emulated chip: 68 % of 12800
 * at 1250 Hz, no late tick). At the next rate dividing 16 MHz, 1600 Hz, the FORCE
 * answering STATE n misses tick n + 1 (delay 2), because the round trip -- the ADC (416
 * cycles), encoding STATE, 31 + 17 bytes on the wire (80 cycles each at 2 Mbaud), the
 * host, decoding FORCE -- takes longer than the 10000-cycle period; at 2 kHz the wire
 * alone takes 48 % of the period and the chip is saturated. */
#ifndef HK_CPU_MAX_RATE_HZ
#define HK_CPU_MAX_RATE_HZ 1250UL /* make bench lifts it to measure 2 and 5 kHz */
#endif
#define HK_MAX_RATE_HZ (HK_LINK_MAX_RATE_HZ < HK_CPU_MAX_RATE_HZ ? HK_LINK_MAX_RATE_HZ : \
                        HK_CPU_MAX_RATE_HZ)
/* With the compact frames (PROTOCOL.md section 4, "Compact frames"; the host asks for them
 * with SENSORS_REQUEST bit COMPACT): a 13-byte STATE_COMPACT up, an 11-byte FORCE_COMPACT
 * down, binary32 values (no binary64 conversion). The round trip on the wire is 24 bytes
 * (1920 cycles at 2 Mbaud), so 4 kHz (a 4000-cycle period) keeps the delay at one tick
 * (tools/bench_firmware.py --compact measures it). */
#define HK_STATE_COMPACT_FRAME_BYTES 13UL
#define HK_LINK_MAX_RATE_COMPACT_HZ (HK_BAUD * HK_LINK_NUM / (HK_LINK_DEN * HK_BITS_PER_BYTE * \
                                                              HK_STATE_COMPACT_FRAME_BYTES))
#ifndef HK_CPU_MAX_RATE_COMPACT_HZ
#define HK_CPU_MAX_RATE_COMPACT_HZ 4000UL
#endif
#define HK_MAX_RATE_COMPACT_HZ (HK_LINK_MAX_RATE_COMPACT_HZ < HK_CPU_MAX_RATE_COMPACT_HZ ? \
                                HK_LINK_MAX_RATE_COMPACT_HZ : HK_CPU_MAX_RATE_COMPACT_HZ)

/* What the tick interrupt puts on the PWM: duty n / 256 (0 = off) and the direction. */
typedef struct {
    uint16_t n;
    uint8_t dir;
} drive_t;

/* ---------------------------------------------------------------- shared with the ISR */
static volatile drive_t g_pending;      /* from the last valid FORCE, applied next tick */
static volatile uint8_t g_has_pending;
static volatile uint32_t g_pending_seq;
static volatile uint8_t g_pending_clamped;
static volatile uint16_t g_wd_reload;   /* ticks a FORCE may be held (watchdog) */
static volatile uint16_t g_wd_left;
static volatile uint8_t g_armed;
static volatile uint8_t g_tick_flag;    /* a tick's sample is in, main loop has not served it */
static volatile uint8_t g_adc_busy;     /* the tick's conversion runs (its ISR ends the tick) */
static volatile uint16_t g_adc_raw;     /* the sample of the last tick [ADC counts] */
static volatile uint8_t g_overrun;      /* a tick came before the last one was served */
static volatile uint32_t g_ticks;       /* ticks since CONFIG (the STATE seq) */
static volatile uint8_t g_tripped;      /* the watchdog zeroed the force this period */
static volatile uint8_t g_trip_event;   /* ... and the FAULT is still to be sent */
static volatile uint32_t g_force_seq;
static volatile uint8_t g_force_applied;
static volatile uint8_t g_clamped_now;
static volatile uint32_t g_period_cycles = F_CPU / HK_NATIVE_RATE_HZ;
/* The device clock at the last tick [cycles] is g_clock_base + ticks * g_period_cycles,
 * ticks = g_tick_wraps * 2^32 + g_ticks (now_us; the tick interrupt only counts). */
static uint64_t g_clock_base;           /* at the last change of period (CONFIG) */
static volatile uint8_t g_tick_wraps;

/* ---------------------------------------------------------------- main loop only */
static uint8_t g_configured, g_fault_latched;
static uint16_t g_limit_n;              /* largest PWM step within the force limit */
static float g_limit_n_float;
static uint32_t g_limit_n_float_bits;   /* g_limit_n_float's bit pattern */
static uint32_t g_limit_n_floor_bits;   /* (float)g_limit_n's */
static uint32_t g_bad_frames, g_bad_reported; /* frames dropped (decoder + lost) */
static uint16_t g_rx_lost_seen;
static uint8_t g_rx_error;
static int16_t g_last_raw;
static int32_t g_offset;                /* turns * span - zero [counts] */
static uint8_t g_have_zero;
static uint8_t g_compact;               /* the host enabled the compact frames */


ISR(TIMER1_COMPA_vect)
{
    /* The tick's new force on the pin and the sample of the sensor (ADC_vect latches it),
     * a few cycles apart, before anything else: the model holds the force and samples the
     * position at the same instant. (Sampled after the bookkeeping and the watchdog, as
     * before, the position was taken ~100 cycles after the new force reached the pin: a
     * fractional advance of the force, 0.6 % of a period at 1 kHz, 2.5 % at 4 kHz, which
     * moved the felt stiffness at 4 kHz past its interval; sampled first, the force came
     * ~35 cycles late and the felt damping fell by about K * 2.2 us.) */
    uint8_t pending = g_has_pending;
    if (pending) {
        pwm_write(g_pending.n, g_pending.dir);
    }
    ADCSRA |= (uint8_t)(1 << ADSC);
    PORTB |= (uint8_t)(1 << PB5); /* budget probe: busy */
    if (pending) {
        g_has_pending = 0;
        g_force_seq = g_pending_seq;
        g_force_applied = 1;
        g_clamped_now = g_pending_clamped;
        g_wd_left = g_wd_reload;
        g_tripped = 0;
    }
    if (g_armed) {
        /* Watchdog: a FORCE received during tick l is held at ticks l+1 .. l+R, with
         * R = floor(W / T) - 1, and zeroed at tick l + floor(W / T) <= its arrival + W. */
        if (g_wd_left == 0) {
            if (!g_tripped) {
                g_tripped = 1;
                g_trip_event = 1;
            }
            pwm_write(0, 0);
            g_clamped_now = 0;
        } else {
            g_wd_left--;
        }
    }
    if (g_tick_flag | g_adc_busy) {
        g_overrun = 1;
    }
    g_adc_busy = 1;
    if (++g_ticks == 0) {
        g_tick_wraps++;
    }
}

/* The conversion started by the tick is done (13 ADC clocks = 416 cycles later, which
 * the MCU sleeps through instead of polling ADSC): latch it and wake the main loop. */
ISR(ADC_vect)
{
    if (g_adc_busy) { /* not a conversion a CONFIG restarted the ticks under */
        g_adc_raw = ADC;
        g_adc_busy = 0;
        g_tick_flag = 1;
    }
}

/* ---------------------------------------------------------------- sending */

static void send(const hp_msg_t *m)
{
    uint8_t frame[HP_MAX_FRAME];
    size_t n = hp_encode(m, frame, sizeof frame);
    if (n) {
        (void)uart_put(frame, n); /* a full ring drops the frame (the host sees a gap) */
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
    m.u.hello.n_axes = 1;
    m.u.hello.device_id = HK_DEVICE_ID;
    m.u.hello.position_scale = f64_of_float((float)HK_POSITION_SCALE_M);
    m.u.hello.force_scale = f64_of_float((float)HK_FORCE_SCALE_N);
    m.u.hello.force_limit = f64_of_float((float)(HK_FORCE_SCALE_N * HK_PWM_STEPS));
    m.u.hello.native_rate_hz = f64_of_float((float)HK_NATIVE_RATE_HZ);
    send(&m);
}

#if F_CPU != 16000000UL
#error "now_us() assumes 16 MHz"
#endif

static uint64_t now_us(void)
{
    uint64_t c;
    uint32_t t, p;
    uint8_t w, s = SREG;
    cli();
    t = g_ticks;
    w = g_tick_wraps;
    p = g_period_cycles;
    SREG = s;
    c = g_clock_base + (((uint64_t)w << 32) | t) * p;
    return c >> 4; /* 16 cycles per microsecond at 16 MHz */
}

/* ---------------------------------------------------------------- timers and ADC */

static void timer1_start(uint32_t period_cycles)
{
    TCCR1B = (uint8_t)(1 << WGM12); /* CTC, clock stopped (OCR1A is written in CTC mode) */
    TCNT1 = 0;
    /* the PWM carrier (Timer0, free-running since reset) restarts with the tick clock, so
     * that its phase at every tick is the same in every session whatever cycle the CONFIG
     * came at (simavr wakes a sleeping core on its timers' events: with the carrier's
     * phase left to the CONFIG's arrival, two lockstep runs differed by one cycle in a
     * tick interrupt's entry, then by one ADC count in 87 of 1200 samples at 4 kHz) */
    TCNT0 = 0;
    TIFR1 = (uint8_t)(1 << OCF1A);
    if (period_cycles <= 65536UL) {
        OCR1A = (uint16_t)(period_cycles - 1u);
        TCCR1B = (uint8_t)((1 << WGM12) | (1 << CS10));            /* CTC, clk / 1 */
    } else {
        OCR1A = (uint16_t)(period_cycles / 8u - 1u);
        TCCR1B = (uint8_t)((1 << WGM12) | (1 << CS11));            /* CTC, clk / 8 */
    }
    TIMSK1 = (uint8_t)(1 << OCIE1A);
}

static void hw_init(void)
{
    DDRD |= (uint8_t)(1 << PD5);                    /* D5: PWM out */
    PORTD &= (uint8_t)~(1 << PD5);
    DDRB |= (uint8_t)((1 << PB0) | (1 << PB5));     /* D8: direction; D13: probe */
    TCCR0A = (uint8_t)((1 << WGM01) | (1 << WGM00)); /* fast PWM 8-bit, OC0B off */
    TCCR0B = (uint8_t)(1 << CS00);                  /* clk / 1: 62.5 kHz */
    OCR0B = 0;
    ADMUX = (uint8_t)((1 << REFS0) | 2u);           /* AVcc reference, ADC2 (A2) */
    DIDR0 = (uint8_t)(1 << ADC2D);
    ADCSRA = (uint8_t)((1 << ADEN) | (1 << ADIE) | (1 << ADPS2) | (1 << ADPS0)); /* clk/32 */
    uart_init();
}

/* ---------------------------------------------------------------- the sensor */

static int32_t read_counts(uint16_t raw)
{
    int16_t d;
    if (!g_have_zero) {
        g_last_raw = (int16_t)raw;
        g_offset = -(int32_t)raw; /* the zero: no turn yet */
        g_have_zero = 1;
    }
    /* flip counting: a jump of more than half a span between two ticks is a wrap; the
     * offset turns * span - zero is kept, not multiplied out each tick */
    d = (int16_t)((int16_t)raw - g_last_raw);
    if (d > (int16_t)(HK_SENSOR_SPAN_COUNTS / 2)) {
        g_offset -= (int32_t)HK_SENSOR_SPAN_COUNTS;
    } else if (d < -(int16_t)(HK_SENSOR_SPAN_COUNTS / 2)) {
        g_offset += (int32_t)HK_SENSOR_SPAN_COUNTS;
    }
    g_last_raw = (int16_t)raw;
    return (int32_t)raw + g_offset;
}

/* ---------------------------------------------------------------- protocol handling */

static void zero_now(void)
{
    uint8_t s = SREG;
    cli();
    g_has_pending = 0;
    pwm_write(0, 0);
    g_clamped_now = 0;
    SREG = s;
}

static void latch_fault(uint16_t code, uint32_t detail)
{
    g_armed = 0;
    g_fault_latched = 1;
    zero_now();
    send_fault(code, detail);
}

static void on_config(const hp_config_t *c)
{
    uint32_t rate = 0, period;
    float limit;
    uint8_t ok = f64_to_u32_exact(c->rate_hz, &rate);
    ok = ok && rate >= HK_MIN_RATE_HZ && (F_CPU % rate) == 0 &&
         rate <= (g_compact ? HK_MAX_RATE_COMPACT_HZ : HK_MAX_RATE_HZ);
    period = ok ? F_CPU / rate : 0;
    ok = ok && (period <= 65536UL || period % 8u == 0);
    /* the watchdog holds a FORCE floor(W / T) - 1 >= 1 ticks: W >= 2 T */
    ok = ok && (uint64_t)c->watchdog_us * rate >= 2000000ULL &&
         (uint64_t)c->watchdog_us * rate / 1000000ULL <= 65535ULL;
    ok = ok && f64_is_finite(c->force_limit) && !(c->force_limit.hi >> 31);
    if (!ok) {
        latch_fault(HP_FAULT_BAD_CONFIG, 0);
        return;
    }
    limit = float_of_f64(c->force_limit);
    if (limit > (float)HK_FORCE_MAX_N) {
        limit = (float)HK_FORCE_MAX_N;
    }
    g_limit_n_float = limit * (float)(HK_PWM_STEPS / HK_FORCE_MAX_N);
    g_limit_n = (uint16_t)g_limit_n_float; /* floor: the pin never exceeds the limit */
    if (g_limit_n > HK_PWM_STEPS) {
        g_limit_n = HK_PWM_STEPS;
    }
    {
        float fl = (float)g_limit_n;
        memcpy(&g_limit_n_floor_bits, &fl, sizeof fl);
        memcpy(&g_limit_n_float_bits, &g_limit_n_float, sizeof fl);
    }
    cli();
    g_clock_base += (((uint64_t)g_tick_wraps << 32) | g_ticks) * g_period_cycles;
    g_tick_wraps = 0;
    g_period_cycles = period;
    g_wd_reload = (uint16_t)((uint64_t)c->watchdog_us * rate / 1000000ULL - 1u);
    g_wd_left = g_wd_reload;
    g_has_pending = 0;
    pwm_write(0, 0);
    g_clamped_now = 0;
    g_tripped = 0;
    g_trip_event = 0;
    g_force_seq = 0;
    g_force_applied = 0;
    g_ticks = 0;
    g_tick_flag = 0;
    g_adc_busy = 0;
    g_overrun = 0;
    g_armed = 1;
    timer1_start(period);
    sei();
    g_configured = 1;
    g_fault_latched = 0;
}

/* A valid FORCE (or FORCE_COMPACT) for STATE `seq`, its force `x` [N] as float32 (+-inf
 * when a finite binary64 is beyond float32: clamped below); `finite`: the value on the
 * wire was finite. */
static void take_force(uint32_t seq, float x, uint8_t finite)
{
    drive_t d;
    uint8_t clamped = 0;
    float ax;
    uint32_t xb, axb;
    if (!g_armed) {
        return;
    }
    if (g_force_applied && (int32_t)(seq - g_force_seq) < 0) {
        return; /* older than the force applied (PROTOCOL.md section 5, rule 4) */
    }
    if (!finite) {
        latch_fault(HP_FAULT_NON_FINITE_FORCE, 0);
        return;
    }
    /* |x| and the comparisons on the bit patterns: for floats >= 0 (no NaN here) the
     * order of the patterns as integers is the order of the values */
    memcpy(&xb, &x, sizeof xb);
    axb = xb & 0x7FFFFFFFUL;
    memcpy(&ax, &axb, sizeof ax);
    ax *= (float)(HK_PWM_STEPS / HK_FORCE_MAX_N); /* in PWM steps */
    memcpy(&axb, &ax, sizeof axb);
    if (axb > g_limit_n_float_bits) {
        clamped = 1;
    }
    if (axb >= g_limit_n_floor_bits) {
        d.n = g_limit_n;
    } else {
        d.n = (uint16_t)(ax + 0.5f); /* nearest step, still <= g_limit_n */
    }
    d.dir = !(xb >> 31) && (xb & 0x7FFFFFFFUL) != 0; /* x > 0 */
    cli();
    g_pending.n = d.n;
    g_pending.dir = d.dir;
    g_pending_seq = seq;
    g_pending_clamped = clamped;
    g_has_pending = 1;
    sei();
}

static void on_force(const hp_force_t *f)
{
    if (f->n_axes != 1) {
        send_fault(HP_FAULT_AXES_MISMATCH, f->n_axes);
        return;
    }
    take_force(f->seq, float_of_f64(f->force[0]), f64_is_finite(f->force[0]));
}

/* FORCE_COMPACT: the 16-bit seq is restored from the tick counter (the FORCE answers a
 * STATE already sent: hp_compact_seq), the binary32 force is used as it is. */
static void force_compact(uint16_t seq16, uint32_t bits)
{
    uint32_t now;
    float x;
    uint8_t s = SREG;
    cli();
    now = g_ticks - 1u; /* the seq of the last tick's STATE */
    SREG = s;
    memcpy(&x, &bits, sizeof x);
    take_force(hp_compact_seq(now, seq16), x, (bits & 0x7F800000UL) != 0x7F800000UL);
}

static void on_force_compact(const hp_force_compact_t *f)
{
    if (f->n_axes != 1) {
        send_fault(HP_FAULT_AXES_MISMATCH, f->n_axes);
        return;
    }
    force_compact(f->seq, f->force[0]);
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
        on_force_compact(&m->u.force_compact);
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
        break;
    case HP_MSG_SENSORS_REQUEST:
        /* The Hapkit 3 measures position only (the MR sensor on the capstan; no
         * tachometer): no sensor offered; the compact frames are (PROTOCOL.md section 4).
         * They start with the next tick's STATE. */
        r.type = HP_MSG_SENSORS;
        r.u.sensors.offered = HP_FEATURE_COMPACT;
        r.u.sensors.enabled = m->u.sensors_request.sensors & HP_FEATURE_COMPACT;
        g_compact = r.u.sensors.enabled != 0;
        send(&r);
        break;
    default:
        break; /* device -> host types are ignored */
    }
}

/* Decode the frame the UART cut out, if one waits; bad frames are dropped and counted.
 * The frame is COBS-decoded as it is taken from the receive ring (uart_packet), then
 * checked and parsed by hp_decode_packet: hp_decode_frame's results in one pass less. */
static void take_frame(void)
{
    static uint8_t pk[HP_MAX_PACKET];
    hp_msg_t m;
    uint8_t len = uart_packet(pk);
    int r;
    if (!len) {
        return;
    }
    if (len == 9u && pk[0] == HP_MSG_FORCE_COMPACT) {
        /* the one frame of every tick in a compact session, 1 axis: checked and taken
         * here (hp_decode_packet's result for it, without its dispatch) */
        if (hp_crc16(0xFFFFu, pk, 9u) == 0) {
            uint32_t bits;
            memcpy(&bits, &pk[3], sizeof bits); /* little-endian, as the wire */
            force_compact(((uint16_t)pk[2] << 8) | pk[1], bits);
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
        g_bad_frames++; /* dropped, counted, never acted on */
        g_rx_error = 1;
    }
}

/* ---------------------------------------------------------------- one tick */

static void serve_tick(void)
{
    hp_msg_t m;
    int32_t counts;
    uint16_t status = 0, lost, raw;
    uint32_t seq, fseq;
    uint8_t s;
    s = SREG;
    cli();
    raw = g_adc_raw;
    g_tick_flag = 0;
    seq = g_ticks - 1u;
    SREG = s;
    counts = read_counts(raw);
    cli();
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
    if (g_fault_latched) {
        status |= HP_STATUS_FAULT;
    }
    if (g_configured) {
        status |= HP_STATUS_CONFIGURED;
    }
    lost = uart_rx_lost();
    if (lost != g_rx_lost_seen) { /* bytes lost: their frames fail and are counted */
        g_rx_lost_seen = lost;
        g_rx_error = 1;
    }
    if (g_rx_error) {
        status |= HP_STATUS_RX_ERROR;
    }
    if (g_compact) {
        /* STATE_COMPACT: seq and status cut to their low bits, the lag saturated at 255
         * (0 before any FORCE), the float32 position as it is; packed here, not through
         * hp_encode (the same bytes: the golden vectors check hp_encode, the closed-loop
         * tests these), to keep the tick's critical path short */
        uint32_t lag = seq - fseq;
        float x = (float)counts * (float)HK_POSITION_SCALE_M;
        uint8_t pk[HK_STATE_COMPACT_FRAME_BYTES - 2u];
        uint16_t crc;
        pk[0] = HP_MSG_STATE_COMPACT;
        pk[1] = (uint8_t)seq;
        pk[2] = (uint8_t)(seq >> 8);
        pk[3] = (uint8_t)status;
        pk[4] = !(status & HP_STATUS_FORCE_APPLIED) ? 0u
                : lag > HP_COMPACT_LAG_MAX ? (uint8_t)HP_COMPACT_LAG_MAX : (uint8_t)lag;
        memcpy(&pk[5], &x, sizeof x); /* little-endian, as the wire */
        crc = hp_crc16(0xFFFFu, pk, 9u);
        pk[9] = (uint8_t)(crc >> 8);
        pk[10] = (uint8_t)crc;
        (void)uart_put_packet(pk, sizeof pk); /* a full ring drops it (a gap) */
    } else {
        m.type = HP_MSG_STATE;
        m.u.state.seq = seq;
        m.u.state.force_seq = fseq;
        m.u.state.time_us = now_us();
        m.u.state.status = status;
        m.u.state.n_axes = 1;
        m.u.state.position[0] = f64_of_float((float)counts * (float)HK_POSITION_SCALE_M);
        send(&m);
    }
    if (g_trip_event) {
        g_trip_event = 0;
        send_fault(HP_FAULT_WATCHDOG, 0);
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
    hw_init();
    timer1_start(g_period_cycles); /* native rate, disarmed: STATE for the host to watch */
    set_sleep_mode(SLEEP_MODE_IDLE);
    sei();
    (void)uart_put(&zero, 1); /* the receiver drops any partial frame */
    send_hello();
    sleep_enable(); /* once: SLEEP is executed only below, so SE may stay set */
    for (;;) {
        /* Every interrupt (a byte sent, a byte received) wakes this loop, ~48 times a
         * tick: the path back to sleep is a few instructions (two flag loads, the probe,
         * sei; sleep -- the instruction after sei runs before any interrupt, so no wake-up
         * is lost between the test and the sleep). */
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
        PORTB &= (uint8_t)~(1 << PB5); /* budget probe: idle */
        sei();
        sleep_cpu();
    }
}
