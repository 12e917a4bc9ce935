/*
 * hapkit_board.c -- the Hapkit 3 board around an emulated ATmega328P (simavr), so the real
 * firmware ELF runs cycle by cycle with the device's physics wired to its pins.
 *
 *   hapkit_board FIRMWARE.elf [options]      prints "PORT /dev/pts/N" on stdout
 *
 * Wiring (Hapkit 3 pinout): the handle's physics is driven by the motor PWM on D5 (Timer0
 * OC0B: duty (OCR0B + 1) / 256 while the compare output drives the pin, else the PORTD5
 * level) and the direction pin D8 (PB0, high = positive force); the force is
 *     F = +-(duty) * T_max * (rs / rp) / rh            (hapkit_geometry.h)
 * on a handle of mass m with viscous friction b0, optional Coulomb friction c, and an
 * optional hand: it holds the handle at 0 until the firmware's first reading (its zero),
 * moves it to x0 and holds it there at rest until the host sends CONFIG, then
 * lets go with velocity v0 (as the hapsim mock restarts its plant at CONFIG); when the host
 * sends STOP it moves the handle back to x0 along a smooth path (at most HAND_MOVE_SPEED,
 * no jump the firmware's flip counting could miss) and holds it there, and a CONFIG that
 * comes before the handle is back lets go at the end of that move; the hand may push
 * with a constant force over a time window after CONFIG. Between two changes of the force the motion
 * m x'' + b0 x' = F is integrated exactly over the emulated time (with Coulomb friction:
 * 1 us steps). The magnetoresistive sensor turns the motor shaft angle
 *     theta_m = x / rh * (rs / rp) + pi * 460 / 921   (x = 0 on the centre of a count)
 * into the voltage of a ratiometric output spanning HK_SENSOR_SPAN_COUNTS ADC counts over
 * each half turn, rounded to the millivolt, fed to ADC2 when the firmware starts a
 * conversion (simavr then quantises it to 10 bits).
 *
 * UART0 is bridged to a new pseudo-terminal on simavr's UART IRQs (input paced by the
 * UART's own FIFO, with its XON/XOFF flow control). Time: --realtime locks the emulated
 * clock to the wall clock; the default (fast, lockstep) runs as fast as the host can
 * answer: after each armed STATE the emulation waits for the host's next frame for as long
 * as the host keeps the port open (or at most --wait-ms of wall time when given), so a slow
 * or loaded host never makes a late FORCE (a 50 ms default cap made one, at random, on a
 * host that paused longer: 1 run in 8 measured another stiffness), and a host that is gone
 * (port closed) leaves the emulation free-running.
 *
 * On SIGINT/SIGTERM or after --duration emulated seconds it writes a JSON report (stdout,
 * or --report FILE): the MCU budget (cycles per tick busy -- ISR + codec + main loop,
 * everything not asleep between two rising edges of the D13 probe -- worst case, idle
 * fraction), the force on the pin (largest magnitude after the first CONFIG, the emulated
 * time it last went to zero), the last valid FORCE from the host, and what the host and the
 * firmware sent (frames, bad frames, FAULT codes).
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_io.h"
#include "sim_irq.h"
#include "avr_adc.h"
#include "avr_uart.h"

#include "../../c/hproto.h"
#include "board_common.h"
#include "../hapkit/hapkit_geometry.h"

/* ATmega328P data-space addresses (datasheet, register summary) */
#define R_PORTB 0x25
#define R_PORTD 0x2B
#define R_TCCR0A 0x44
#define R_OCR0B 0x48
#define COM0B1_BIT 5

#define F_CPU_HZ 16000000UL
#define CYCLES_PER_US 16u

/* ---------------------------------------------------------------- options */
/* Real time: the longest spin per tick waiting for the host's FORCE [us] (--spin-us; 0:
 * never spin). See `win`. */
#define SPIN_US_DEFAULT 0.0


static struct {
    const char *elf;
    int realtime;
    double mass, friction, coulomb, x0, v0;
    double hand_force, hand_start, hand_duration;
    double wait_ms, duration;
    const char *report, *link, *profile, *trace;
    double spin_us;
} opt = {NULL, 0, 0.1, 0.5, 0.0, 0.005, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, NULL, NULL, NULL, NULL,
         SPIN_US_DEFAULT};

/* --profile: cycles spent at each flash word while armed and awake (the MCU budget by
 * instruction; tools/bench_firmware.py --profile maps them to functions and lines) */
#define PROFILE_WORDS 16384u /* 32 KiB of flash */
static uint64_t profile_cycles[PROFILE_WORDS];

/* ---------------------------------------------------------------- the board */
static avr_t *avr;
static int master = -1;
static volatile sig_atomic_t stop_signal;

static struct {
    double x, v;        /* handle [m], [m/s] */
    double f_motor;     /* [N] */
    uint64_t cyc;       /* emulated time of (x, v) [cycles] */
    uint64_t config_cyc;
    int configured;
    /* the hand's move of the handle to x0 (at STOP, and at CONFIG when not there yet): it
     * holds the handle on a raised-cosine path (the motor does not move it), then holds it
     * at rest at x0 (after STOP) or lets go with v0 (after CONFIG) */
    int moving, held, release, zero_read;
    /* a CONFIG taken with the handle held at rest at x0: the hand lets go at the first
     * tick after the firmware's first armed STATE (release_armed: waiting for that STATE;
     * release_tick: at the next conversion), so that the motion starts at the same cycle
     * of the firmware's new tick clock in every run. Let go when the board read the
     * CONFIG (a cycle the wall clock chose: the board paces a disarmed firmware in real
     * time), two lockstep runs differed by one ADC count in 274 of 1000 samples; let go
     * at tick 0's conversion (found when STATE 0 came out, the handle moved on from
     * there) they still differed (k 507.305 and 507.322 N/m); let go at tick 1, 6 runs
     * of 6 gave the same telemetry bit for bit at 1 kHz (k 507.2901), 4 of them with the
     * board stopped 0.12 s every 0.3 s, but 4 kHz runs still differed by one ADC count in
     * 22-87 of 1200 samples: the PWM carrier (Timer0) ran free from reset, so its phase
     * against the new tick clock was the CONFIG's wall-chosen cycle, and simavr, which
     * wakes a sleeping core on its timers' events, entered a tick interrupt one cycle
     * apart. The firmware now restarts the carrier with the tick clock (main.c,
     * timer1_start): traced with --trace, two runs are the same cycle for cycle from the
     * first armed tick on. With v0 = 0
     * nothing moves the handle over tick 0 either way (no FORCE is applied before tick
     * 1); a v0 starts one period late (the free response is the same loop's). */
    int release_armed, release_tick;
    double move_from, move_to;
    uint64_t move_start, move_cycles;
} ph;

/* Fastest the hand moves the handle [m/s]: at 1 m/s the handle moves 1 mm per 1 kHz tick,
 * far below the half sensor period (8.1 mm of handle travel) the firmware's flip counting
 * can follow; a jump (the board placed the handle at x0 at once, before) made it count the
 * wrong number of turns: the next run started 0.27 m away with 18 J stored. */
#define HAND_MOVE_SPEED 1.0

static struct {
    uint16_t n;
    uint8_t dir;
    int init;
} drive;

static struct {
    uint64_t ticks, busy_sum, busy_max, cycles_sum, window_busy, window_start;
    uint64_t armed_cycles, armed_busy; /* every cycle while the firmware is armed */
    uint8_t probe;
    int counting;
    double rate_hz;
    uint32_t watchdog_us;
} budget;

static struct {
    double max_abs_force;      /* after the first CONFIG [N] */
    uint64_t last_nonzero_cyc; /* last emulated time the pin force was not zero */
    uint64_t zero_since_cyc;   /* the pin force has been zero since (when zero_valid) */
    int zero_valid;
    double force_now;
} pin;

static struct {
    hp_decoder_t dec_host, dec_fw;
    uint64_t host_frames_ok, host_bad, fw_states, fw_faults[16], fw_bad;
    uint64_t last_force_cyc;   /* last valid FORCE from the host, fully received */
    int have_force;
    double last_force_value;
    uint64_t waits, wait_timeouts, tx_dropped;
    uint8_t in_q[4096];
    size_t in_head, in_tail;
    int xon;
    int await_host, host_present;
    /* lockstep: the seq of the armed STATE the host is to answer; what the host sent, as
     * read from the pty (before the UART takes it): the newest FORCE seq of this session
     * (since the last CONFIG), a STOP not followed by a CONFIG (the firmware disarms: no
     * answer comes, even to a STATE it sent before it took the STOP), any other frame
     * since the STATE (a host that does not answer it: a handshake) */
    uint32_t await_seq, read_force_seq;
    int read_force_valid, read_stop, read_other, compact;
    hp_decoder_t dec_read;
    uint8_t out[64];
    size_t out_n;
    uint16_t fw_status;
    uint64_t fw_status_rx_error, fw_overrun;
    uint32_t fw_rx_errors_detail;
} link_;

static avr_irq_t *uart_irq, *adc_irq;

/* Where the wall time goes (report "time"): emulating (avr_run), the pty and UART bridge,
 * sleeping to hold real time; real time: the emulated clock slips (never races to catch
 * up) when the process fell behind the wall clock by more than SLIP_NS. */
#define SLIP_NS 2000000u
/* How far the emulated clock may run ahead of the wall clock [ns]: each microsecond of lead
 * is taken from the host's time to answer a STATE before the next tick. */
#define LEAD_NS 50000u
static struct {
    uint64_t emulate_ns, io_ns, sleep_ns, spin_ns, armed_emulate_ns, armed_cycles, slips,
        slipped_ns;
    uint64_t behind_max_ns;
} tm;

/* --trace FILE: the board's events with the emulated cycle and the wall clock
 * (CLOCK_MONOTONIC, the clock the host's time.monotonic_ns reads), kept in memory and
 * written at exit, one line each (tools/bench_firmware.py --trace reads them):
 *   T cyc wall late_ns                a tick starts (D13 rises); late_ns: wall - schedule
 *   A cyc wall mv x v                 the firmware starts a conversion of ADC2 (x [m], v [m/s])
 *   P cyc wall n dir                  the motor PWM changes (duty steps, direction)
 *   S cyc wall seq status force_seq   the firmware's STATE left the UART (last byte)
 *   R cyc wall seq                    a host FORCE read from the pty (whole frame)
 *   F cyc wall type seq               a host frame handed to the UART (last byte)
 *   W cyc wall want_ns over_ns spun_ns a wait for the wall clock (real time) ended over_ns
 *                                      after its target (a sleep, then a spin of spun_ns)
 * late_ns is -1 while the clock is not locked to the wall (fast mode, armed). Two lockstep
 * runs compare by their cycles and values (columns 2 and 4 on), not by the wall. */
typedef struct {
    char kind;
    uint64_t cyc, wall;
    double a, b, c;
} trace_ev_t;
#define TRACE_MAX (1u << 20)
static trace_ev_t *trace_buf;
static size_t trace_n;
static uint64_t trace_dropped;

static uint64_t wall_ns(void);
/* the wall clock the emulated clock is locked to (emulated cycle 0 at wall0 [ns]) while
 * `paced` (real time, or fast mode pacing a disarmed firmware) */
static uint64_t wall0;
static int paced;

static void trace(char kind, uint64_t cyc, double a, double b, double c)
{
    if (!trace_buf) {
        return;
    }
    if (trace_n >= TRACE_MAX) {
        trace_dropped++;
        return;
    }
    trace_buf[trace_n].kind = kind;
    trace_buf[trace_n].cyc = cyc;
    trace_buf[trace_n].wall = wall_ns();
    trace_buf[trace_n].a = a;
    trace_buf[trace_n].b = b;
    trace_buf[trace_n].c = c;
    trace_n++;
}

/* Real time, --spin-us S > 0: from an armed STATE until the host's FORCE answering it is
 * read (or S us of wall time have passed), the board emulates in WINDOW_CHUNK steps and
 * spins to the wall clock between them, never ahead of it. The bytes of a FORCE enter the
 * UART at the emulated cycle the board has reached when they are read: with 100 us chunks
 * run ahead of the wall clock and a sleep after each, that cycle is up to 100 us (on
 * average 50 us) after the wall time the FORCE came at, taken from the host's time to
 * answer (traced: a FORCE must reach the UART ~240 us before the tick to be applied at it).
 * The spin costs at most S us of CPU per tick (time.spin_s). */
#define WINDOW_CHUNK 160u /* 10 us */
static struct {
    int open;
    uint64_t since; /* [ns] wall */
} win;

static double hand_force_at(uint64_t cyc)
{
    double t;
    if (!ph.configured || opt.hand_force == 0.0) {
        return 0.0;
    }
    t = (double)(cyc - ph.config_cyc) / F_CPU_HZ;
    return (t >= opt.hand_start && t < opt.hand_start + opt.hand_duration) ? opt.hand_force
                                                                           : 0.0;
}

/* Exact motion of m x'' + b0 x' = f over dt [s] with f constant. */
static void exact_step(double f, double dt)
{
    double m = opt.mass, b = opt.friction;
    if (b > 0.0) {
        double vinf = f / b, a = exp(-b * dt / m);
        ph.x += vinf * dt + (ph.v - vinf) * (m / b) * (1.0 - a);
        ph.v = vinf + (ph.v - vinf) * a;
    } else {
        ph.x += ph.v * dt + 0.5 * f / m * dt * dt;
        ph.v += f / m * dt;
    }
}

/* Start the hand's move of the handle from where it is to x0: peak speed HAND_MOVE_SPEED,
 * velocity zero at both ends (x = a + (b - a)(1 - cos(pi s))/2, s in [0, 1]); `release`:
 * let go with v0 at its end (CONFIG), else hold at rest there (STOP). */
static void hand_move_to_x0(int release)
{
    double d = fabs(opt.x0 - ph.x);
    ph.move_from = ph.x;
    ph.move_to = opt.x0;
    ph.move_start = ph.cyc;
    ph.move_cycles = (uint64_t)ceil(M_PI / 2.0 * d / HAND_MOVE_SPEED * F_CPU_HZ);
    ph.moving = 1;
    ph.held = 1;
    ph.release = release;
}

/* The hand's path at `cyc` (inside the move): position and velocity. */
static void hand_path(uint64_t cyc)
{
    double span = ph.move_to - ph.move_from, T = (double)ph.move_cycles / F_CPU_HZ;
    double sfrac = T > 0 ? (double)(cyc - ph.move_start) / (double)ph.move_cycles : 1.0;
    ph.x = ph.move_from + span * (1.0 - cos(M_PI * sfrac)) / 2.0;
    ph.v = T > 0 ? span * M_PI / (2.0 * T) * sin(M_PI * sfrac) : 0.0;
}

static void advance_to(uint64_t cyc)
{
    while (ph.held && ph.cyc < cyc) {
        uint64_t end = ph.move_start + ph.move_cycles;
        if (ph.moving && cyc < end) {
            ph.cyc = cyc;
            hand_path(cyc);
            return;
        }
        if (ph.moving) {                 /* the move ends at `end` */
            ph.cyc = end;
            ph.x = ph.move_to;
            ph.v = 0.0;
            ph.moving = 0;
        }
        if (ph.release) {                /* the hand lets go at x0 with v0 */
            ph.held = 0;
            ph.v = opt.v0;
        } else {                         /* held at rest at x0 until CONFIG */
            ph.cyc = cyc;
            return;
        }
    }
    while (ph.cyc < cyc) {
        uint64_t next = cyc;
        double f;
        if (opt.hand_force != 0.0 && ph.configured) {
            /* split at the hand's switching times */
            uint64_t on = ph.config_cyc + (uint64_t)(opt.hand_start * F_CPU_HZ);
            uint64_t off = ph.config_cyc +
                           (uint64_t)((opt.hand_start + opt.hand_duration) * F_CPU_HZ);
            if (ph.cyc < on && on < next) {
                next = on;
            }
            if (ph.cyc < off && off < next) {
                next = off;
            }
        }
        if (opt.coulomb > 0.0 && next - ph.cyc > CYCLES_PER_US) {
            next = ph.cyc + CYCLES_PER_US;
        }
        f = ph.f_motor + hand_force_at(ph.cyc);
        if (opt.coulomb > 0.0) {
            if (ph.v == 0.0 && fabs(f) <= opt.coulomb) {
                ph.cyc = next; /* sticking */
                continue;
            }
            {
                double v0 = ph.v, fc = (ph.v != 0.0 ? (ph.v > 0 ? -1.0 : 1.0)
                                                    : (f > 0 ? -1.0 : 1.0)) * opt.coulomb;
                exact_step(f + fc, (double)(next - ph.cyc) / F_CPU_HZ);
                if ((v0 > 0 && ph.v < 0) || (v0 < 0 && ph.v > 0)) {
                    ph.v = 0.0; /* friction stops the handle within the step */
                }
            }
        } else {
            exact_step(f, (double)(next - ph.cyc) / F_CPU_HZ);
        }
        ph.cyc = next;
    }
}

static void sample_drive(void)
{
    uint8_t tccr0a = avr->data[R_TCCR0A], portd = avr->data[R_PORTD];
    uint8_t portb = avr->data[R_PORTB];
    uint16_t n;
    uint8_t dir = portb & 1u, probe = (portb >> 5) & 1u;
    if (tccr0a & (1u << COM0B1_BIT)) {
        n = (uint16_t)(avr->data[R_OCR0B] + 1u);
    } else {
        n = (portd & (1u << 5)) ? HK_PWM_STEPS : 0u;
    }
    if (!drive.init || n != drive.n || dir != drive.dir) {
        double f = (dir ? 1.0 : -1.0) * (double)n * HK_FORCE_MAX_N / HK_PWM_STEPS;
        advance_to(avr->cycle);
        drive.init = 1;
        drive.n = n;
        drive.dir = dir;
        ph.f_motor = f;
        pin.force_now = f;
        if (n != 0) {
            pin.zero_valid = 0;
        } else if (!pin.zero_valid) {
            pin.zero_since_cyc = avr->cycle;
            pin.zero_valid = 1;
        }
        trace('P', avr->cycle, n, dir, 0);
        if (ph.configured && fabs(f) > pin.max_abs_force) {
            pin.max_abs_force = fabs(f);
        }
    }
    if (n != 0) {
        pin.last_nonzero_cyc = avr->cycle;
    }
    if (probe && !budget.probe) { /* a tick starts: close the last window */
        if (trace_buf) {
            double late = -1.0;
            if (paced) {
                late = (double)wall_ns() - ((double)wall0 + (double)avr->cycle * 1e9 / F_CPU_HZ);
            }
            trace('T', avr->cycle, late, 0, 0);
        }
        if (budget.counting) {
            uint64_t len = avr->cycle - budget.window_start;
            budget.ticks++;
            budget.busy_sum += budget.window_busy;
            budget.cycles_sum += len;
            if (budget.window_busy > budget.busy_max) {
                budget.busy_max = budget.window_busy;
            }
        }
        budget.counting = (link_.fw_status & HP_STATUS_ARMED) != 0;
        budget.window_start = avr->cycle;
        budget.window_busy = 0;
    }
    budget.probe = probe;
}

/* ---------------------------------------------------------------- sensor */

static void adc_trigger(struct avr_irq_t *irq, uint32_t value, void *param)
{
    union {
        avr_adc_mux_t mux;
        uint32_t v;
    } e = {.v = value};
    double theta, phi, counts, mv;
    (void)irq;
    (void)param;
    if (e.mux.kind != ADC_MUX_SINGLE || e.mux.src != 2) {
        return;
    }
    advance_to(avr->cycle);
    if (ph.release_tick) { /* the hand lets go now, at this tick (see release_armed) */
        ph.release_tick = 0;
        ph.held = 0;
        ph.v = opt.v0;
    }
    /* x = 0 at the middle of a half turn, on the centre of an ADC count (511) */
    theta = ph.x / HK_HANDLE_LENGTH_M * (HK_SECTOR_RADIUS_M / HK_CAPSTAN_RADIUS_M) +
            HK_SENSOR_PERIOD_RAD * (HK_SENSOR_SPAN_COUNTS / 2) / HK_SENSOR_SPAN_COUNTS;
    phi = fmod(theta, HK_SENSOR_PERIOD_RAD);
    if (phi < 0) {
        phi += HK_SENSOR_PERIOD_RAD;
    }
    counts = HK_SENSOR_LO_COUNTS + HK_SENSOR_SPAN_COUNTS * phi / HK_SENSOR_PERIOD_RAD;
    /* the ADC reads floor(mV * 1023 / 5000): centre each count on its voltage */
    mv = floor((counts + 0.5) * HK_ADC_VREF_MV / HK_ADC_MAX + 0.5);
    avr_raise_irq(adc_irq + ADC_IRQ_ADC2, (uint32_t)mv);
    trace('A', avr->cycle, mv, ph.x, ph.v);
    /* the firmware takes its zero from its first reading it keeps (it drops a conversion
     * a CONFIG restarted the ticks under): the hand moves to x0 after the third */
    if (ph.zero_read < 3 && ++ph.zero_read == 3) {
        hand_move_to_x0(ph.configured); /* a CONFIG before it: let go at the end */
    }
}

/* ---------------------------------------------------------------- UART <-> pty */

/* Whether the FORCE seq the host sent last answers the STATE awaited, or a later one: in
 * 32 bits, or in 16 bits in a compact session (STATE_COMPACT and FORCE_COMPACT carry the
 * low 16 bits of the seq, PROTOCOL.md section 4). */
static int force_answers_await(void)
{
    if (link_.compact) {
        return (int16_t)(uint16_t)(link_.read_force_seq - link_.await_seq) >= 0;
    }
    return (int32_t)(link_.read_force_seq - link_.await_seq) >= 0;
}

static void on_fw_state(uint32_t seq, uint16_t status, int compact)
{
    link_.fw_states++;
    link_.fw_status = status;
    link_.compact = compact;
    if (status & HP_STATUS_RX_ERROR) {
        link_.fw_status_rx_error++;
    }
    if (status & HP_STATUS_OVERRUN) {
        link_.fw_overrun++;
    }
    if (ph.release_armed && (status & HP_STATUS_ARMED) &&
        !(status & HP_STATUS_FORCE_APPLIED)) {
        /* the firmware's first STATE of the new session (tick 0): let go at tick 1 */
        ph.release_armed = 0;
        ph.release_tick = 1;
    }
    if ((status & HP_STATUS_ARMED) && link_.host_present) {
        link_.await_host = 1; /* fast mode: let the host answer this STATE */
        link_.await_seq = seq;
        link_.read_other = 0;
    }
}

static void on_fw_msg(const hp_msg_t *m)
{
    if (m->type == HP_MSG_STATE) {
        trace('S', avr->cycle, m->u.state.seq, m->u.state.status, m->u.state.force_seq);
        on_fw_state(m->u.state.seq, m->u.state.status, 0);
    } else if (m->type == HP_MSG_STATE_COMPACT) {
        trace('S', avr->cycle, m->u.state_compact.seq, m->u.state_compact.status,
              (double)m->u.state_compact.seq - m->u.state_compact.lag);
        on_fw_state(m->u.state_compact.seq, m->u.state_compact.status, 1);
    } else if (m->type == HP_MSG_FAULT) {
        link_.fw_faults[m->u.fault.code & 15u]++;
        if (m->u.fault.code == HP_FAULT_RX_ERRORS) {
            link_.fw_rx_errors_detail = m->u.fault.detail;
        }
    }
}

/* Write the firmware's bytes held so far to the pty (dropped, counted, when no host reads
 * and the pty is full). */
static void flush_out(void)
{
    if (link_.out_n && master >= 0) {
        ssize_t w = write(master, link_.out, link_.out_n);
        if (w < (ssize_t)link_.out_n) {
            link_.tx_dropped += link_.out_n - (w > 0 ? (size_t)w : 0u);
        }
    }
    link_.out_n = 0;
}

static void uart_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    uint8_t b = (uint8_t)value;
    hp_msg_t m;
    int r;
    (void)irq;
    (void)param;
    link_.out[link_.out_n++] = b;
    if (b == 0 || link_.out_n == sizeof link_.out) {
        flush_out(); /* a whole frame per write: one wake-up of the host, not one a byte */
    }
    r = hp_decoder_feed(&link_.dec_fw, b, &m);
    if (r == HP_OK) {
        on_fw_msg(&m);
    } else if (r != HP_NONE) {
        link_.fw_bad++;
    }
}

static void uart_xon(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value) {
        link_.xon = 1; /* the UART's input FIFO has room */
    }
}

static void uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    link_.xon = value ? 0 : 1; /* raised with 1 when the FIFO is full, 0 when not */
}

static void on_host_msg(const hp_msg_t *m)
{
    link_.host_frames_ok++;
    trace('F', avr->cycle, m->type,
          m->type == HP_MSG_FORCE ? (double)m->u.force.seq
          : m->type == HP_MSG_FORCE_COMPACT ? (double)m->u.force_compact.seq : -1.0, 0);
    if (m->type == HP_MSG_CONFIG) {
        /* the hand lets go of the handle at x0 with v0 (the mock's plant restarts there at
         * CONFIG); a handle not there yet is moved there first, without a jump */
        advance_to(avr->cycle);
        if (ph.zero_read < 3) {
            /* the firmware has not read its zero yet: the move waits for it (adc_trigger) */
        } else if (!ph.held || ph.moving || ph.x != opt.x0) {
            if (!ph.moving) {
                hand_move_to_x0(1);
            }
            ph.release = 1;
        } else {
            ph.release_armed = 1; /* let go at the firmware's first armed tick */
        }
        ph.configured = 1;
        ph.config_cyc = avr->cycle;
        budget.rate_hz = m->u.config.rate_hz;
        budget.watchdog_us = m->u.config.watchdog_us;
    } else if (m->type == HP_MSG_STOP) {
        /* the run is over: the hand brings the handle back to x0 and holds it there */
        advance_to(avr->cycle);
        ph.release_armed = 0;
        ph.release_tick = 0;
        if (ph.zero_read >= 3 && (!ph.held || ph.release)) {
            if (!ph.moving) {
                hand_move_to_x0(0);
            }
            ph.release = 0;
        }
    } else if (m->type == HP_MSG_FORCE) {
        link_.last_force_cyc = avr->cycle;
        link_.have_force = 1;
        link_.last_force_value = m->u.force.force[0];
    } else if (m->type == HP_MSG_FORCE_COMPACT) {
        float x;
        memcpy(&x, &m->u.force_compact.force[0], sizeof x);
        link_.last_force_cyc = avr->cycle;
        link_.have_force = 1;
        link_.last_force_value = x;
    }
}

/* Hand the queued host bytes to the UART while its FIFO has room. */
static void feed_uart(void)
{
    while (link_.xon && link_.in_tail != link_.in_head) {
        uint8_t b = link_.in_q[link_.in_tail];
        hp_msg_t m;
        int r;
        link_.in_tail = (link_.in_tail + 1u) % sizeof link_.in_q;
        avr_raise_irq(uart_irq + UART_IRQ_INPUT, b);

        r = hp_decoder_feed(&link_.dec_host, b, &m);
        if (r == HP_OK) {
            on_host_msg(&m);
        } else if (r != HP_NONE) {
            link_.host_bad++;
        }
    }
}

/* Read what the host wrote; wait up to `timeout_ms` for something. */
static void read_host(int timeout_ms)
{
    struct pollfd pfd = {master, POLLIN, 0};
    int r = poll(&pfd, 1, timeout_ms);
    link_.host_present = !(pfd.revents & POLLHUP);
    if (r > 0 && (pfd.revents & POLLIN)) {
        uint8_t buf[256];
        size_t room = (link_.in_tail + sizeof link_.in_q - link_.in_head - 1u) %
                      sizeof link_.in_q; /* host far ahead of the UART: rest stays in pty */
        ssize_t n = read(master, buf, room < sizeof buf ? room : sizeof buf);
        ssize_t i;
        for (i = 0; i < n; i++) {
            hp_msg_t m;
            link_.in_q[link_.in_head] = buf[i];
            link_.in_head = (link_.in_head + 1u) % sizeof link_.in_q;
            if (hp_decoder_feed(&link_.dec_read, buf[i], &m) == HP_OK) {
                if (m.type == HP_MSG_FORCE || m.type == HP_MSG_FORCE_COMPACT) {
                    link_.read_force_seq = m.type == HP_MSG_FORCE ? m.u.force.seq
                                                                  : m.u.force_compact.seq;
                    link_.read_force_valid = 1;
                    trace('R', avr->cycle, link_.read_force_seq, 0, 0);
                } else {
                    link_.read_other = 1;
                    if (m.type == HP_MSG_STOP) {
                        link_.read_stop = 1;
                    } else if (m.type == HP_MSG_CONFIG) {
                        link_.read_stop = 0;
                        link_.read_force_valid = 0;
                    }
                }
            }
        }
    }
}



/* ---------------------------------------------------------------- report */

static void report(int code)
{
    FILE *f = opt.report ? fopen(opt.report, "w") : stdout;
    double us = 1.0 / CYCLES_PER_US;
    double period = budget.rate_hz > 0 ? F_CPU_HZ / budget.rate_hz : 0;
    if (!f) {
        f = stdout;
    }
    advance_to(avr->cycle);
    fprintf(f, "{\"exit\": \"%s\", \"emulated_s\": %.9f, \"mode\": \"%s\",\n",
            code == 0 ? "ok" : "firmware stopped", (double)avr->cycle / F_CPU_HZ,
            opt.realtime ? "realtime" : "fast");
    /* per tick: between rising edges of the D13 probe (none when the MCU never sleeps: it
     * is saturated); over the whole armed run: the share of cycles not asleep */
    fprintf(f, " \"budget\": {\"rate_hz\": %.6g, \"period_cycles\": %.0f, \"ticks\": %llu, "
               "\"busy_mean_cycles\": %.1f, \"busy_max_cycles\": %llu, "
               "\"idle_fraction\": %.6f, \"saturated\": %s},\n",
            budget.rate_hz, period, (unsigned long long)budget.ticks,
            budget.armed_cycles && period > 0
                ? (double)budget.armed_busy / ((double)budget.armed_cycles / period) : 0.0,
            (unsigned long long)budget.busy_max,
            budget.armed_cycles ? 1.0 - (double)budget.armed_busy / budget.armed_cycles : 0.0,
            budget.armed_cycles > 20 * period && budget.ticks < 2 ? "true" : "false");
    fprintf(f, " \"pin\": {\"max_abs_force_n\": %.9g, \"force_now_n\": %.9g, "
               "\"zero_since_us\": %.3f, \"last_nonzero_us\": %.3f, \"force_step_n\": %.9g, "
               "\"force_max_n\": %.9g},\n",
            pin.max_abs_force, pin.force_now,
            pin.force_now == 0 ? (double)pin.zero_since_cyc * us : -1.0,
            (double)pin.last_nonzero_cyc * us, HK_FORCE_MAX_N / HK_PWM_STEPS, HK_FORCE_MAX_N);
    fprintf(f, " \"host\": {\"frames_ok\": %llu, \"bad_frames\": %llu, \"watchdog_us\": %u, "
               "\"last_force_us\": %.3f, \"last_force_n\": %.17g, \"waits\": %llu, "
               "\"wait_timeouts\": %llu},\n",
            (unsigned long long)link_.host_frames_ok, (unsigned long long)link_.host_bad,
            budget.watchdog_us, link_.have_force ? (double)link_.last_force_cyc * us : -1.0,
            link_.last_force_value, (unsigned long long)link_.waits,
            (unsigned long long)link_.wait_timeouts);
    fprintf(f, " \"firmware\": {\"states\": %llu, \"bad_frames\": %llu, "
               "\"states_rx_error\": %llu, \"states_overrun\": %llu, "
               "\"fault_rx_errors_detail\": %u, \"faults\": {",
            (unsigned long long)link_.fw_states, (unsigned long long)link_.fw_bad,
            (unsigned long long)link_.fw_status_rx_error,
            (unsigned long long)link_.fw_overrun, link_.fw_rx_errors_detail);
    {
        int i, first = 1;
        for (i = 0; i < 16; i++) {
            if (link_.fw_faults[i]) {
                fprintf(f, "%s\"%d\": %llu", first ? "" : ", ", i,
                        (unsigned long long)link_.fw_faults[i]);
                first = 0;
            }
        }
    }
    fprintf(f, "}, \"tx_dropped\": %llu},\n", (unsigned long long)link_.tx_dropped);
    fprintf(f, " \"time\": {\"emulate_s\": %.6f, \"io_s\": %.6f, \"sleep_s\": %.6f, "
               "\"spin_s\": %.6f, \"spin_us\": %.1f, "
               "\"armed_mhz\": %.3f, \"slips\": %llu, \"slipped_s\": %.6f, "
               "\"behind_max_ms\": %.3f, \"trace_dropped\": %llu},\n",
            tm.emulate_ns * 1e-9, tm.io_ns * 1e-9, tm.sleep_ns * 1e-9, tm.spin_ns * 1e-9,
            opt.spin_us,
            tm.armed_emulate_ns ? tm.armed_cycles * 1e3 / (double)tm.armed_emulate_ns : 0.0,
            (unsigned long long)tm.slips, tm.slipped_ns * 1e-9, tm.behind_max_ns * 1e-6,
            (unsigned long long)trace_dropped);
    fprintf(f, " \"simavr\": {\"warnings\": %llu, \"last_warning\": \"",
            (unsigned long long)simlog.warnings);
    simlog_json(f);
    fprintf(f, "\"},\n");
    fprintf(f, " \"handle\": {\"x_m\": %.9g, \"v_m_s\": %.9g, \"mass_kg\": %.9g, "
               "\"friction_n_s_m\": %.9g, \"coulomb_n\": %.9g}}\n",
            ph.x, ph.v, opt.mass, opt.friction, opt.coulomb);
    if (f != stdout) {
        fclose(f);
    }
}

/* ---------------------------------------------------------------- main */

static void on_signal(int s)
{
    stop_signal = s;
}

/* Cycles the MCU spent asleep. simavr runs a SLEEP instruction and the sleep after it in
 * one avr_run call (cycle += 1 + how_long after the instruction's own cycle), and a call
 * that starts asleep may end in an interrupt's entry: so the busy cycles of a call are
 * its cycles minus what this hook saw slept, not "the call started running". */
static uint64_t slept_cycles;

static void noop_sleep(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    slept_cycles += 1u + how_long;
}

static double num(const char *s, const char *name)
{
    return board_num(s, name, "hapkit_board");
}

static void usage(void)
{
    fprintf(stderr,
            "usage: hapkit_board FIRMWARE.elf [--realtime] [--mass KG] [--friction NS_M]\n"
            "         [--coulomb N] [--x0 M] [--v0 M_S] [--hand-force N --hand-start S\n"
            "         --hand-duration S] [--wait-ms MS] [--duration S] [--report FILE]\n"
            "         [--link PATH] [--profile FILE] [--trace FILE] [--spin-us US]\n");
    exit(2);
}


static uint64_t wall_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

/* Wait until the wall clock reads `target` [ns], taking the host's bytes as they come: a
 * wait on the pty (ppoll) until `target` less `spin` [ns], then a spin to `target` that
 * checks the pty without waiting. Each frame the host writes meanwhile is read and handed
 * to the UART at once (at the emulated cycle the board has reached), not at the end of
 * the wait. A wake-up from a sleep is late by the timer's and the scheduler's latency, most
 * of all when the core sat idle (it first leaves its idle state); a spin pays CPU for a
 * wake-up on time (report "time": sleep_s, spin_s; trace: W). */
static void wait_until(uint64_t target, uint64_t spin)
{
    uint64_t t0 = wall_ns(), now = t0, spun = 0;
    uint64_t spin_from = 0;
    while (now < target && !stop_signal) {
        struct pollfd pfd = {master, POLLIN, 0};
        int r;
        if (target - now > spin) {
            uint64_t left = target - spin - now;
            struct timespec ts = {(time_t)(left / 1000000000u), (long)(left % 1000000000u)};
            if (link_.host_present) {
                r = ppoll(&pfd, 1, &ts, NULL);
            } else { /* no host: the pty hangs up at once, sleep instead */
                r = 0;
                nanosleep(&ts, NULL);
            }
        } else {
            if (!spin_from) {
                spin_from = now;
            }
            r = poll(&pfd, 1, 0);
        }
        if (r > 0 && (pfd.revents & (POLLIN | POLLHUP))) {
            read_host(0);     /* the host's bytes now: into the queue, and to the UART */
            feed_uart();
        }
        now = wall_ns();
    }
    spun = spin_from ? now - spin_from : 0;
    tm.sleep_ns += now - t0 - spun;
    tm.spin_ns += spun;
    trace('W', avr->cycle, target > t0 ? (double)(target - t0) : 0.0,
          (double)now - (double)target, (double)spun);
}

int main(int argc, char **argv)
{
    elf_firmware_t fw;
    uint32_t flags = 0;
    int i, code = 0, pace;
    uint64_t chunk = 1600; /* 100 us of emulated time between host polls */
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "--realtime")) {
            opt.realtime = 1;
            continue;
        }
        if (a[0] != '-') {
            opt.elf = a;
            continue;
        }
        if (!v) {
            usage();
        }
        i++;
        if (!strcmp(a, "--mass")) opt.mass = num(v, a);
        else if (!strcmp(a, "--friction")) opt.friction = num(v, a);
        else if (!strcmp(a, "--coulomb")) opt.coulomb = num(v, a);
        else if (!strcmp(a, "--x0")) opt.x0 = num(v, a);
        else if (!strcmp(a, "--v0")) opt.v0 = num(v, a);
        else if (!strcmp(a, "--hand-force")) opt.hand_force = num(v, a);
        else if (!strcmp(a, "--hand-start")) opt.hand_start = num(v, a);
        else if (!strcmp(a, "--hand-duration")) opt.hand_duration = num(v, a);
        else if (!strcmp(a, "--wait-ms")) opt.wait_ms = num(v, a);
        else if (!strcmp(a, "--duration")) opt.duration = num(v, a);
        else if (!strcmp(a, "--report")) opt.report = v;
        else if (!strcmp(a, "--link")) opt.link = v;
        else if (!strcmp(a, "--profile")) opt.profile = v;
        else if (!strcmp(a, "--trace")) opt.trace = v;
        else if (!strcmp(a, "--spin-us")) opt.spin_us = num(v, a);
        else usage();
    }
    if (!opt.elf || !(opt.mass > 0) || opt.friction < 0 || opt.coulomb < 0 ||
        opt.spin_us < 0 || opt.spin_us > 1000) {
        usage();
    }
    if (opt.trace && !(trace_buf = malloc(TRACE_MAX * sizeof *trace_buf))) {
        fprintf(stderr, "hapkit_board: no memory for --trace\n");
        return 1;
    }
    avr_global_logger_set(log_stderr);
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(opt.elf, &fw)) {
        fprintf(stderr, "hapkit_board: cannot read %s\n", opt.elf);
        return 2;
    }
    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr) {
        fprintf(stderr, "hapkit_board: simavr has no atmega328p core\n");
        return 1;
    }
    avr_init(avr);
    avr->log = 0;
    avr->frequency = F_CPU_HZ;
    avr->vcc = avr->avcc = avr->aref = HK_ADC_VREF_MV;
    avr_load_firmware(avr, &fw);
    avr->frequency = F_CPU_HZ;
    avr->vcc = avr->avcc = avr->aref = HK_ADC_VREF_MV;
    avr->sleep = noop_sleep; /* the board keeps time itself (fast or real-time) */

    ph.held = 1; /* the hand holds the handle at rest at 0, the firmware's zero, until
                  * its first reading, then moves it to x0 and holds it until CONFIG */
    hp_decoder_init(&link_.dec_host);
    hp_decoder_init(&link_.dec_read);
    hp_decoder_init(&link_.dec_fw);
    link_.xon = 0; /* until the firmware enables its receiver (simavr signals XON then) */
    uart_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), 0);
    adc_irq = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, 0);
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUTPUT, uart_out, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XON, uart_xon, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XOFF, uart_xoff, NULL);
    avr_irq_register_notify(adc_irq + ADC_IRQ_OUT_TRIGGER, adc_trigger, NULL);

    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    signal(SIGPIPE, SIG_IGN);
    master = board_open_pty(opt.link, "hapkit_board");
    link_.host_present = 0;
    wall0 = wall_ns();
    while (!stop_signal) {
        uint64_t end = avr->cycle + (win.open ? WINDOW_CHUNK : chunk);
        if (opt.duration > 0 && (double)avr->cycle >= opt.duration * F_CPU_HZ) {
            break;
        }
        uint64_t t_a = wall_ns(), c_a = avr->cycle, t_b;
        while (avr->cycle < end && !link_.await_host) {
            uint64_t c0 = avr->cycle, s0 = slept_cycles, busy;
            uint32_t pc0 = (uint32_t)avr->pc;
            int st = avr_run(avr);
            if (st == cpu_Done || st == cpu_Crashed) {
                fprintf(stderr, "hapkit_board: firmware stopped (state %d) at %.6f s\n", st,
                        (double)avr->cycle / F_CPU_HZ);
                code = 1;
                goto done;
            }
            busy = (avr->cycle - c0) - (slept_cycles - s0);
            budget.window_busy += busy;
            if (link_.fw_status & HP_STATUS_ARMED) {
                budget.armed_cycles += avr->cycle - c0;
                budget.armed_busy += busy;
                if (opt.profile && busy) {
                    profile_cycles[(pc0 >> 1) % PROFILE_WORDS] += busy;
                }
            }
            sample_drive();
        }
        t_b = wall_ns();
        tm.emulate_ns += t_b - t_a;
        if (link_.fw_status & HP_STATUS_ARMED) {
            tm.armed_emulate_ns += t_b - t_a;
            tm.armed_cycles += avr->cycle - c_a;
        }
        flush_out();
        read_host(0);
        if (link_.await_host && opt.realtime && opt.spin_us > 0) {
            win.open = 1; /* an armed STATE is out: watch for its FORCE (see win) */
            win.since = wall_ns();
        }
        if (win.open && ((link_.read_force_valid && force_answers_await()) ||
                         link_.read_stop || !link_.host_present ||
                         (double)(wall_ns() - win.since) > opt.spin_us * 1e3)) {
            win.open = 0;
        }
        if (link_.await_host && !opt.realtime) {
            /* fast mode: wait (wall time) for the host's answer to this STATE */
            uint64_t w0 = wall_ns();
            link_.waits++;
            /* until the host's FORCE answering this STATE is read (a frame read before
             * the STATE ended cannot be it), or a STOP (maybe read before this STATE
             * ended, not taken yet), or another frame since it */
            while (!(link_.read_force_valid && force_answers_await()) &&
                   !link_.read_stop && !link_.read_other && link_.host_present &&
                   !stop_signal) {
                uint64_t el = (wall_ns() - w0) / 1000000u;
                if (opt.wait_ms > 0 && (double)el >= opt.wait_ms) {
                    link_.wait_timeouts++;
                    break;
                }
                read_host(opt.wait_ms > 0 ? (int)(opt.wait_ms - (double)el) + 1 : 100);
            }
        }
        link_.await_host = 0;
        feed_uart();
        tm.io_ns += wall_ns() - t_b;
        /* real time: always with --realtime; in fast mode while a host listens to a
         * disarmed device (its STATEs would flood the host as fast as the host can read) */
        pace = opt.realtime ||
               (link_.host_present && !(link_.fw_status & HP_STATUS_ARMED));
        if (pace) {
            uint64_t emu = (uint64_t)((double)avr->cycle * 1e9 / F_CPU_HZ);
            uint64_t wall;
            if (!paced) {
                wall0 = wall_ns() - emu; /* lock from here on */
            }
            wall = wall_ns() - wall0;
            if (win.open && emu > wall) {
                wait_until(wall0 + emu, UINT64_MAX); /* spin: see win */
            } else if (emu > wall + LEAD_NS) {
                wait_until(wall0 + emu, 0);
            } else if (wall > emu + SLIP_NS) {
                /* descheduled or too slow: slip, do not race the firmware's ticks through
                 * the lost time (a host answering in real time would be late for each) */
                tm.slips++;
                tm.slipped_ns += wall - emu;
                if (wall - emu > tm.behind_max_ns) {
                    tm.behind_max_ns = wall - emu;
                }
                wall0 += wall - emu;
            }
        }
        paced = pace;
    }
done:
    report(code);
    if (trace_buf) {
        FILE *tf = fopen(opt.trace, "w");
        size_t k;
        if (tf) {
            for (k = 0; k < trace_n; k++) {
                const trace_ev_t *e = &trace_buf[k];
                fprintf(tf, "%c %llu %llu %.17g %.17g %.17g\n", e->kind,
                        (unsigned long long)e->cyc, (unsigned long long)e->wall, e->a, e->b,
                        e->c);
            }
            fclose(tf);
        }
    }
    if (opt.profile) {
        FILE *pf = fopen(opt.profile, "w");
        unsigned w;
        if (pf) {
            for (w = 0; w < PROFILE_WORDS; w++) {
                if (profile_cycles[w]) {
                    fprintf(pf, "%#x %llu\n", 2u * w, (unsigned long long)profile_cycles[w]);
                }
            }
            fclose(pf);
        }
    }
    return code;
}
