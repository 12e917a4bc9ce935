/*
 * pantograph_board.c -- the Hapkit pantograph around two emulated ATmega328P (simavr) on one
 * TWI bus: the leader and follower firmware ELFs (../pantograph) run cycle by cycle, each
 * driving one proximal joint of a five-bar linkage whose joint-space dynamics this process
 * integrates.
 *
 *   pantograph_board LEADER.elf FOLLOWER.elf [options]    prints "PORT /dev/pts/N"
 *   pantograph_board --plant-test [options] < torques      the plant alone (tests)
 *
 * The plant (hapsim.joint_device.JointDeviceND transcribed): joints q = (q1, q2) [rad],
 *     (Mq + mh J^T J) q'' = tau - Bq q' - bh J^T J q' - mh J^T a_b,
 * J = dx/dq of the five-bar (the larger-y closure, hapsim.kinematics.Pantograph), a_b the
 * handle's acceleration bias d^2 f(q + s q')/ds^2 by the same central second difference
 * (step 1e-4 / |q'| rad), the torques held between two changes of either motor's drive;
 * classical Runge-Kutta in equal steps of at most --substep seconds (default 0.5 ms: two per
 * period at 1 kHz, as the Python model). Each joint is a Hapkit 3 capstan drive
 * (hapkit_geometry.h): joint torque = +-(duty) T_max rs / rp on each motor's D5/D8, motor
 * shaft angle = (q - home) rs / rp + pi * 460 / 921 into that board's MR sensor on ADC2.
 *
 * The bus: simavr 1.6 models the TWI master (its status after each byte) but not a slave
 * that another core runs; this board is the wire between the two cores. On the leader's
 * TWI output it answers at once what the bus would (ACK or NACK of the address and of each
 * byte written, the byte the follower holds in TWDR for a read) and gives the follower's
 * TWI what its hardware would see, at the cycle the leader's status comes (own SLA+W 0x60,
 * general call 0x70, a byte 0x80, STOP 0xA0, own SLA+R 0xA8, byte taken 0xB8/0xC0): the
 * status in TWSR, the byte in TWDR, the TWI interrupt raised. A follower that has not
 * served its last TWI interrupt when the next event is due holds the bus (clock
 * stretching): the event waits for it, and is counted. The follower acknowledges its
 * address (or the general call, with TWGCE) when its TWI is enabled with TWEA;
 * --nack-after N withholds the follower's acknowledge from the N-th transaction on (a
 * follower gone from the bus). The two cores run in step (each at most FENCE cycles
 * ahead of the other).
 *
 * The hand: it holds the handle at the home (the calibration block written into the
 * leader's EEPROM: --geometry, --home) until the host's CONFIG; at the k-th CONFIG since the
 * host's last HELLO_REQUEST it puts the handle at start k mod 5 of
 * hapsim.lockstep.excitation_starts (rest; a along x; a along y; moving at a / (10 T)
 * along x; along y; T the CONFIG's period) at rest and lets go at the session's first
 * tick (the first SYNC after the firmware took the CONFIG), with the start's velocity; at
 * STOP it holds the handle where it is.
 *
 * Time. Lockstep (the default): after each armed STATE the emulated clock waits for the
 * host's FORCE answering it, so the wire's time is emulated and a slow host is never late;
 * --host-latency-us L hands each FORCE to the UART L us of emulated time after the STATE's
 * last byte left (a host that answers in L us: tools/bench_pantograph.py --host-slack finds
 * the largest L that keeps the delay at one tick, in emulated cycles, whatever the load).
 * --realtime locks the emulated clock (the leader's; the follower never more than FENCE
 * cycles from it) to the wall clock (CLOCK_MONOTONIC), as hapkit_board --realtime: the
 * cores run in chunks of 100 us of emulated time at most LEAD_NS ahead of the wall clock
 * and wait for it on the pty (a byte the host writes meanwhile is handed to the UART at
 * once, at the emulated cycle reached: never earlier than the wall time it came at, so
 * the host never gains time); a board that fell more than SLIP_NS behind (descheduled,
 * too slow) slips its clock instead of racing the firmware's ticks through the lost time
 * (counted: time.slips, slipped_s; the plant and the firmware see no gap, the emulated
 * time is continuous). With --spin-us S > 0, from an armed STATE until the FORCE answering
 * it is read (or S us have passed) the board emulates in 10 us steps and spins to the
 * wall clock between them, never ahead of it by more than a step: the bytes then reach
 * the UART within 10 us of the wall time they came at (the full STATE leaves the host
 * ~80 us at 1 kHz, docs/pantograph.md). A FORCE that comes too late for its tick is held
 * back by the firmware to the next one and its STATE says so (force_seq): the host's
 * account of late ticks. On SIGINT/SIGTERM or after --duration emulated seconds it writes
 * a JSON report (stdout or --report FILE): the cycle budget of each MCU per tick, the bus,
 * the frames, the plant, the time.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stddef.h>
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
#include "sim_cycle_timers.h"
#include "sim_interrupts.h"
#include "avr_adc.h"
#include "avr_eeprom.h"
#include "avr_twi.h"
#include "avr_uart.h"

#include "../../c/hproto.h"
#include "board_common.h"
#include "../hapkit/hapkit_geometry.h"
#include "../pantograph/pantograph_link.h"

#define R_PORTB 0x25
#define R_PORTD 0x2B
#define R_TCCR0A 0x44
#define R_OCR0B 0x48
#define R_TWSR 0xB9
#define R_TWAR 0xBA
#define R_TWDR 0xBB
#define R_TWCR 0xBC
#define TWINT_BIT 7
#define TWEA_BIT 6
#define TWEN_BIT 2
#define COM0B1_BIT 5
#define F_CPU_HZ 16000000.0
#define TWI_BYTE_CYCLES 144u /* simavr 1.6: 9 bus clocks of one microsecond */
#define FENCE 64u            /* cycles a core may run ahead of the other */

enum { LEAD = 0, FOLL = 1 };

/* ---------------------------------------------------------------- options */
static struct {
    const char *elf[2];
    double l1, l2, L1, L2, d, home[2];
    double Mq[4], Bq[4], mh, bh, amplitude, substep, duration;
    long nack_after;
    const char *report, *link, *profile;
    int plant_test, realtime;
    double spin_us, host_latency_us;
} opt = {{NULL, NULL}, 0.05, 0.05, 0.07, 0.07, 0.02, {2.26892802759263, 0.872664625997165},
         {2e-4, 0, 0, 2e-4}, {1e-3, 0, 0, 1e-3}, 0.0, 0.0, 1e-8, 5e-4, 0.0, -1, NULL, NULL, NULL, 0,
         0, 0.0, 0.0};

/* Real time (hapkit_board's rules): the emulated clock slips when it fell more than
 * SLIP_NS behind the wall clock, and runs at most LEAD_NS ahead of it (each microsecond of
 * lead is taken from the host's time to answer); --spin-us steps of WINDOW_CHUNK cycles. */
#define SLIP_NS 2000000u
#define LEAD_NS 50000u
#define WINDOW_CHUNK 160u /* 10 us */
static struct {
    uint64_t emulate_ns, io_ns, sleep_ns, spin_ns, slips, slipped_ns, behind_max_ns;
    uint64_t armed_emulate_ns, armed_cycles;
} tm;
static struct {
    int open;
    uint64_t since; /* [ns] wall */
} win;
static uint64_t wall0; /* the wall clock [ns] at emulated cycle 0 while paced */
static int paced;

static avr_t *core[2];
static int last_fed_type; /* the last host frame handed to the leader's UART */

static avr_twi_t *twi[2];
static avr_irq_t *adc_irq[2], *uart_irq;
static volatile sig_atomic_t stop_signal;
static int master = -1;

/* ---------------------------------------------------------------- five-bar */

/* Handle (x, y) and J (row-major) at q; 0 when there is no assembly or J is singular. */
static int five_bar(const double q[2], double x[2], double J[4])
{
    double c1 = cos(q[0]), s1 = sin(q[0]), c2 = cos(q[1]), s2 = sin(q[1]);
    double ax = opt.l1 * c1, ay = opt.l1 * s1, bx = opt.d + opt.l2 * c2, by = opt.l2 * s2;
    double r = hypot(bx - ax, by - ay), ex, ey, along, h, px, py;
    double pax, pay, pbx, pby, cross, d1, d2;
    if (!(fabs(opt.L1 - opt.L2) < r && r < opt.L1 + opt.L2)) {
        return 0;
    }
    ex = (bx - ax) / r;
    ey = (by - ay) / r;
    along = (opt.L1 * opt.L1 - opt.L2 * opt.L2 + r * r) / (2.0 * r);
    h = sqrt(fmax(opt.L1 * opt.L1 - along * along, 0.0));
    if (ex < 0) {
        h = -h;
    }
    px = ax + along * ex - h * ey;
    py = ay + along * ey + h * ex;
    x[0] = px;
    x[1] = py;
    if (!J) {
        return 1;
    }
    pax = px - ax;
    pay = py - ay;
    pbx = px - bx;
    pby = py - by;
    cross = pax * pby - pay * pbx;
    d1 = opt.l1 * (-pax * s1 + pay * c1);
    d2 = opt.l2 * (-pbx * s2 + pby * c2);
    if (cross == 0.0) {
        return 0;
    }
    J[0] = pby * d1 / cross;
    J[1] = -pay * d2 / cross;
    J[2] = -pbx * d1 / cross;
    J[3] = pax * d2 / cross;
    return 1;
}

/* ---------------------------------------------------------------- the plant */
static struct {
    double q[2], qd[2], tau[2];
    uint64_t cyc;
    int held;           /* the hand holds the handle at rest */
    int release_armed;  /* 1: a CONFIG was fed; 2: the firmware took it (DRIVE seen) */
    double v_release[2];
    int configs;        /* CONFIGs since the host's last HELLO_REQUEST */
    long configs_total; /* CONFIGs since power-up */
    double period;      /* the last CONFIG's period [s] */
    uint64_t rk_steps, bad_kinematics, big_jumps;
} ph;

static int accel(const double q[2], const double qd[2], double out[2])
{
    double x[2], J[4], xp[2], xm[2], bias[2] = {0, 0}, A[4], b[2], JtJ[4], Jqd[2], det;
    double speed = hypot(qd[0], qd[1]);
    if (!five_bar(q, x, J)) {
        return 0;
    }
    if (speed > 0) {
        double eps = 1e-4 / speed, qp[2], qm[2];
        qp[0] = q[0] + eps * qd[0];
        qp[1] = q[1] + eps * qd[1];
        qm[0] = q[0] - eps * qd[0];
        qm[1] = q[1] - eps * qd[1];
        if (!five_bar(qp, xp, NULL) || !five_bar(qm, xm, NULL)) {
            return 0;
        }
        bias[0] = (xp[0] - 2 * x[0] + xm[0]) / (eps * eps);
        bias[1] = (xp[1] - 2 * x[1] + xm[1]) / (eps * eps);
    }
    JtJ[0] = J[0] * J[0] + J[2] * J[2];
    JtJ[1] = J[0] * J[1] + J[2] * J[3];
    JtJ[2] = JtJ[1];
    JtJ[3] = J[1] * J[1] + J[3] * J[3];
    Jqd[0] = JtJ[0] * qd[0] + JtJ[1] * qd[1];
    Jqd[1] = JtJ[2] * qd[0] + JtJ[3] * qd[1];
    b[0] = ph.tau[0] - (opt.Bq[0] * qd[0] + opt.Bq[1] * qd[1]) - opt.bh * Jqd[0] -
           opt.mh * (J[0] * bias[0] + J[2] * bias[1]);
    b[1] = ph.tau[1] - (opt.Bq[2] * qd[0] + opt.Bq[3] * qd[1]) - opt.bh * Jqd[1] -
           opt.mh * (J[1] * bias[0] + J[3] * bias[1]);
    A[0] = opt.Mq[0] + opt.mh * JtJ[0];
    A[1] = opt.Mq[1] + opt.mh * JtJ[1];
    A[2] = opt.Mq[2] + opt.mh * JtJ[2];
    A[3] = opt.Mq[3] + opt.mh * JtJ[3];
    det = A[0] * A[3] - A[1] * A[2];
    out[0] = (A[3] * b[0] - A[1] * b[1]) / det;
    out[1] = (-A[2] * b[0] + A[0] * b[1]) / det;
    return 1;
}

/* One classical Runge-Kutta step of h [s] with the torques held. */
static void rk4(double h)
{
    double *q = ph.q, *v = ph.qd, k1[2], k2[2], k3[2], k4[2], qt[2], v2[2], v3[2], v4[2];
    int i, ok = accel(q, v, k1);
    for (i = 0; i < 2; i++) {
        qt[i] = q[i] + 0.5 * h * v[i];
        v2[i] = v[i] + 0.5 * h * k1[i];
    }
    ok = ok && accel(qt, v2, k2);
    for (i = 0; i < 2; i++) {
        qt[i] = q[i] + 0.5 * h * v2[i];
        v3[i] = v[i] + 0.5 * h * k2[i];
    }
    ok = ok && accel(qt, v3, k3);
    for (i = 0; i < 2; i++) {
        qt[i] = q[i] + h * v3[i];
        v4[i] = v[i] + h * k3[i];
    }
    ok = ok && accel(qt, v4, k4);
    if (!ok) {
        ph.bad_kinematics++;
        return; /* the handle stays: the report says so */
    }
    for (i = 0; i < 2; i++) {
        q[i] += h / 6.0 * (v[i] + 2.0 * v2[i] + 2.0 * v3[i] + v4[i]);
        v[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
    }
    ph.rk_steps++;
}

/* Integrate over dt [s] in equal steps of at most opt.substep. */
static void integrate(double dt)
{
    long n, i;
    if (dt <= 0) {
        return;
    }
    n = (long)ceil(dt / opt.substep - 1e-9);
    if (n < 1) {
        n = 1;
    }
    for (i = 0; i < n; i++) {
        rk4(dt / (double)n);
    }
}

static void advance_to(uint64_t cyc)
{
    if (cyc <= ph.cyc) {
        return; /* the other core asked a few cycles later already */
    }
    if (!ph.held) {
        integrate((double)(cyc - ph.cyc) / F_CPU_HZ);
    }
    ph.cyc = cyc;
}

/* ---------------------------------------------------------------- the hand */

/* Joints with f(q) = target, Newton from the current joints; 0 when it fails. */
static int joints_at(const double target[2], double q[2])
{
    int it;
    q[0] = ph.q[0];
    q[1] = ph.q[1];
    for (it = 0; it < 20; it++) {
        double x[2], J[4], det, e0, e1;
        if (!five_bar(q, x, J)) {
            return 0;
        }
        e0 = target[0] - x[0];
        e1 = target[1] - x[1];
        det = J[0] * J[3] - J[1] * J[2];
        q[0] += (J[3] * e0 - J[1] * e1) / det;
        q[1] += (-J[2] * e0 + J[0] * e1) / det;
        if (fabs(e0) + fabs(e1) < 1e-15) {
            break;
        }
    }
    return 1;
}

/* CONFIG k: the handle at start k at rest, let go with its velocity at the first tick. */
static void hand_on_config(double rate_hz)
{
    double rest[2], x[2], v[2] = {0, 0}, q[2], J[4], det, T = 1.0 / rate_hz;
    int k = ph.configs++ % 5;
    ph.configs_total++;
    double a = opt.amplitude;
    five_bar(opt.home, rest, NULL);
    x[0] = rest[0] + (k == 1 ? a : 0.0);
    x[1] = rest[1] + (k == 2 ? a : 0.0);
    if (k == 3) {
        v[0] = a / (10.0 * T);
    } else if (k == 4) {
        v[1] = a / (10.0 * T);
    }
    ph.period = T;
    if (!joints_at(x, q)) {
        ph.bad_kinematics++;
        return;
    }
    /* a jump the firmware's flip counting follows: under a quarter of a sensor period */
    if (fabs(q[0] - ph.q[0]) > HK_SENSOR_PERIOD_RAD / 4 * HK_CAPSTAN_RADIUS_M /
                                   HK_SECTOR_RADIUS_M ||
        fabs(q[1] - ph.q[1]) > HK_SENSOR_PERIOD_RAD / 4 * HK_CAPSTAN_RADIUS_M /
                                   HK_SECTOR_RADIUS_M) {
        ph.big_jumps++;
    }
    ph.q[0] = q[0];
    ph.q[1] = q[1];
    ph.qd[0] = ph.qd[1] = 0.0;
    five_bar(q, x, J);
    det = J[0] * J[3] - J[1] * J[2];
    ph.v_release[0] = (J[3] * v[0] - J[1] * v[1]) / det;
    ph.v_release[1] = (-J[2] * v[0] + J[0] * v[1]) / det;
    ph.held = 1;
    ph.release_armed = 1;
}

/* ---------------------------------------------------------------- motors, sensors */
static struct {
    uint16_t n;
    uint8_t dir, init;
} drive[2];

static double tau_of(uint16_t n, uint8_t dir)
{
    return (dir ? 1.0 : -1.0) * (double)n / HK_PWM_STEPS * HK_MOTOR_TORQUE_MAX_NM *
           HK_SECTOR_RADIUS_M / HK_CAPSTAN_RADIUS_M;
}

static struct {
    uint64_t ticks, busy_sum[2], busy_max[2], window_busy[2], window_start;
    uint64_t armed_cycles, armed_busy[2];
    uint8_t probe;
    int counting, armed;
    double rate_hz;
} budget;

static uint64_t slept[2];
/* --profile: the leader's busy cycles at each flash word while armed (the budget by
 * instruction; tools/bench_pantograph.py maps them to functions) */
static uint64_t prof[16384];


static void sample_drive(int c)
{
    avr_t *a = core[c];
    uint8_t tccr0a = a->data[R_TCCR0A], portd = a->data[R_PORTD], portb = a->data[R_PORTB];
    uint16_t n;
    uint8_t dir = portb & 1u;
    if (tccr0a & (1u << COM0B1_BIT)) {
        n = (uint16_t)(a->data[R_OCR0B] + 1u);
    } else {
        n = (portd & (1u << 5)) ? HK_PWM_STEPS : 0u;
    }
    if (!drive[c].init || n != drive[c].n || dir != drive[c].dir) {
        advance_to(a->cycle);
        drive[c].init = 1;
        drive[c].n = n;
        drive[c].dir = dir;
        ph.tau[c] = tau_of(n, dir);
    }
    if (c == LEAD) {
        uint8_t probe = (portb >> 5) & 1u;
        if (probe && !budget.probe) {
            if (budget.counting) {
                int i;
                budget.ticks++;
                for (i = 0; i < 2; i++) {
                    budget.busy_sum[i] += budget.window_busy[i];
                    if (budget.window_busy[i] > budget.busy_max[i]) {
                        budget.busy_max[i] = budget.window_busy[i];
                    }
                }
            }
            budget.counting = budget.armed;
            budget.window_start = a->cycle;
            budget.window_busy[0] = budget.window_busy[1] = 0;
        }
        budget.probe = probe;
    }
}

static void adc_trigger(struct avr_irq_t *irq, uint32_t value, void *param)
{
    int c = (int)(intptr_t)param;
    union {
        avr_adc_mux_t mux;
        uint32_t v;
    } e = {.v = value};
    double theta, phi, counts, mv;
    (void)irq;
    if (e.mux.kind != ADC_MUX_SINGLE || e.mux.src != 2) {
        return;
    }
    advance_to(core[c]->cycle);
    if (c == LEAD && ph.release_armed == 3) {
        /* the session's first tick: the hand lets go now (both joints are sampled here) */
        ph.release_armed = 0;
        ph.held = 0;
        ph.qd[0] = ph.v_release[0];
        ph.qd[1] = ph.v_release[1];
    }
    theta = (ph.q[c] - opt.home[c]) * (HK_SECTOR_RADIUS_M / HK_CAPSTAN_RADIUS_M) +
            HK_SENSOR_PERIOD_RAD * (HK_SENSOR_SPAN_COUNTS / 2) / HK_SENSOR_SPAN_COUNTS;
    phi = fmod(theta, HK_SENSOR_PERIOD_RAD);
    if (phi < 0) {
        phi += HK_SENSOR_PERIOD_RAD;
    }
    counts = HK_SENSOR_LO_COUNTS + HK_SENSOR_SPAN_COUNTS * phi / HK_SENSOR_PERIOD_RAD;
    mv = floor((counts + 0.5) * HK_ADC_VREF_MV / HK_ADC_MAX + 0.5);
    avr_raise_irq(adc_irq[c] + ADC_IRQ_ADC2, (uint32_t)mv);
}

/* ---------------------------------------------------------------- the TWI wire */
enum { EV_NONE = 0 };
typedef struct {
    uint64_t due;     /* leader-clock cycle the follower's status comes */
    uint8_t status;   /* TWSR */
    int has_data;
    uint8_t data;     /* into TWDR */
} twi_event_t;

static struct {
    twi_event_t q[8];
    unsigned head, tail;
    int addressed;       /* the follower is in a transaction: 1 receiver, 2 transmitter */
    int general;         /* ... by the general call */
    long transactions, nack_addr, nack_data, stretched, bytes_w, bytes_r, overflow;
    long armed_transactions;   /* since the first CONFIG (--nack-after counts these) */
    /* the critical path: from a DRIVE's end to the next SYNC (armed ticks) [cycles] */
    uint64_t drive_end, last_sync, slack_min, slack_sum, slack_n;
    /* a DRIVE on the bus, its START to its STOP [leader cycles]: the longest */
    uint64_t drive_start, drive_max;
    int f_busy;          /* the follower's TWINT: raised by an event, cleared by its write */
    int pending_read, read_ack;   /* the leader asked a byte the follower has not given */
    uint8_t read_addr;
    uint64_t read_asked;
    long late_bytes;
    uint8_t last_sync_status;
} bus;

static int follower_acks(void)
{
    avr_t *f = core[FOLL];
    uint8_t twcr = f->data[R_TWCR];
    if (opt.nack_after >= 0 && ph.configs_total && bus.armed_transactions > opt.nack_after) {
        return 0;
    }
    return (twcr & (1u << TWEN_BIT)) && (twcr & (1u << TWEA_BIT));
}

/* The follower has not served its last TWI event yet (TWINT still 1 to it). */
static int follower_twint(void)
{
    return bus.f_busy;
}

static void follower_apply(const twi_event_t *e)
{
    avr_t *f = core[FOLL];
    if (e->has_data) {
        f->data[R_TWDR] = e->data;
    }
    avr_regbit_setto_raw(f, twi[FOLL]->twsr, e->status);
    bus.f_busy = 1;
    avr_raise_interrupt(f, &twi[FOLL]->twi);
}

static void bus_pump(void);
static void read_byte(void);

/* The follower wrote TWCR (after simavr's own handler): TWINT written 1 clears the flag
 * and releases the bus (simavr 1.6 keeps TWI's flag "sticky": it would stay 1). */
static void follower_twcr(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)addr;
    (void)param;
    if (v & (1u << TWINT_BIT)) {
        a->data[R_TWCR] &= (uint8_t)~(1u << TWINT_BIT);
        bus.f_busy = 0;
        bus_pump();
        if (bus.pending_read && !bus.f_busy && bus.tail == bus.head) {
            read_byte();
        }
    }
}

/* Deliver the due events the follower is ready for (its last TWI interrupt served). */
static void bus_pump(void)
{
    while (bus.tail != bus.head) {
        twi_event_t *e = &bus.q[bus.tail % 8u];
        if (e->due > core[FOLL]->cycle) {
            return;
        }
        if (follower_twint()) {
            return; /* the follower holds SCL low: the event waits (stretched) */
        }
        if (e->due + 2u < core[FOLL]->cycle) {
            bus.stretched++;
        }
        follower_apply(e);
        bus.tail++;
    }
}

static avr_cycle_count_t bus_timer(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    bus_pump();
    return 0;
}

static void bus_post(uint64_t due, uint8_t status, int has_data, uint8_t data)
{
    twi_event_t *e;
    if (bus.head - bus.tail >= 8u) {
        bus.overflow++;
        return;
    }
    e = &bus.q[bus.head % 8u];
    e->due = due;
    e->status = status;
    e->has_data = has_data;
    e->data = data;
    bus.head++;
    if (due > core[FOLL]->cycle) {
        avr_cycle_timer_register(core[FOLL], due - core[FOLL]->cycle, bus_timer, e);
    }
}

static void reply_leader(uint8_t msg, uint8_t addr, uint8_t data)
{
    avr_raise_irq(twi[LEAD]->io.irq + TWI_IRQ_INPUT, avr_twi_irq_msg(msg, addr, data));
}

/* The leader's TWI put something on the bus (simavr 1.6's master messages). */
static void leader_twi_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    avr_twi_msg_irq_t m;
    uint64_t now = core[LEAD]->cycle;
    (void)irq;
    (void)param;
    m.u.v = value;
    if (m.u.twi.msg & TWI_COND_STOP) {
        if (bus.addressed == 1) {
            bus_post(now + 2u, 0xA0, 0, 0); /* STOP while addressed as receiver */
            if (!bus.general && now - bus.drive_start > bus.drive_max) {
                bus.drive_max = now - bus.drive_start;
            }
            if (!bus.general && budget.armed && (last_fed_type == HP_MSG_FORCE ||
                                                      last_fed_type == HP_MSG_FORCE_COMPACT)) {
                bus.drive_end = now; /* a FORCE's DRIVE done: the critical path ends */
            }
        }
        bus.addressed = 0;
        return;
    }
    if (m.u.twi.msg & TWI_COND_START) {
        /* the address byte: the master's status comes at once when it had written TWDR
         * (simavr 1.6 reports the data state then), else after a byte time */
        uint8_t sla = m.u.twi.addr;
        int rd = sla & 1u, gc = (sla >> 1) == 0;
        uint8_t own = core[FOLL]->data[R_TWAR];
        uint64_t due = now + ((!rd && (twi[LEAD]->state & TWI_COND_WRITE)) ? 1u
                                                                           : TWI_BYTE_CYCLES);
        int match = gc ? ((own & 1u) && !rd) : ((sla >> 1) == (own >> 1));
        int ack;
        bus.transactions++;
        if (ph.configs_total) {
            bus.armed_transactions++;
        }
        ack = match && follower_acks();
        reply_leader(TWI_COND_ACK, sla, (uint8_t)ack);
        if (!ack) {
            bus.nack_addr++;
            bus.addressed = 0;
            return;
        }
        bus.general = gc;
        bus.addressed = rd ? 2 : 1;
        if (!gc && !rd) {
            bus.drive_start = now; /* its address byte (the START is ~60 cycles before) */
        }
        if (gc && !rd) {
            /* a SYNC: the slack of the last tick (its DRIVE's end to this tick) */
            if (bus.drive_end > bus.last_sync && budget.armed) {
                uint64_t slack = now - bus.drive_end;
                if (!bus.slack_n || slack < bus.slack_min) {
                    bus.slack_min = slack;
                }
                bus.slack_sum += slack;
                bus.slack_n++;
            }
            bus.last_sync = now;
        }
        if (gc && ph.release_armed == 2 && !rd) {
            ph.release_armed = 3; /* the session's first SYNC: let go at its samples */
        }
        bus_post(due, rd ? 0xA8 : (gc ? 0x70 : 0x60), rd ? 0 : 1, sla);
        return;
    }
    if (bus.addressed == 1 && (m.u.twi.msg & TWI_COND_WRITE)) {
        int ack = follower_acks();
        reply_leader(TWI_COND_ACK, m.u.twi.addr, (uint8_t)ack);
        if (!ack) {
            bus.nack_data++;
        }
        bus.bytes_w++;
        if (!bus.general && ph.release_armed == 1) {
            ph.release_armed = 2; /* the firmware took the CONFIG: its DRIVE of zero */
        }
        bus_post(now + TWI_BYTE_CYCLES, bus.general ? (ack ? 0x90 : 0x98) : (ack ? 0x80 : 0x88),
                 1, m.u.twi.data);
        return;
    }
    if (bus.addressed == 2 && (m.u.twi.msg & TWI_COND_READ)) {
        /* the byte the follower puts in TWDR: now when it has served its last TWI
         * event, else when it does (it holds SCL low until then: read_byte) */
        bus.read_ack = (m.u.twi.msg & TWI_COND_ACK) != 0;
        bus.read_addr = m.u.twi.addr;
        bus.read_asked = now;
        bus.pending_read = 1;
        if (!follower_twint() && bus.tail == bus.head) {
            read_byte();
        }
        return;
    }
}

/* Hand the leader the byte the follower holds in TWDR, then give the follower its status
 * a byte time later: ACK from the master (more wanted) or NACK (the last). A byte handed
 * later than the master's own byte time would find the master's TWDR already read: it is
 * counted (late_bytes). */
static void read_byte(void)
{
    uint64_t now = core[FOLL]->cycle;
    bus.pending_read = 0;
    if (now > bus.read_asked + TWI_BYTE_CYCLES) {
        bus.late_bytes++;
    } else if (now > bus.read_asked + 2u) {
        bus.stretched++;
    }
    reply_leader(TWI_COND_READ, bus.read_addr, core[FOLL]->data[R_TWDR]);
    bus.bytes_r++;
    bus_post(now + TWI_BYTE_CYCLES, bus.read_ack ? 0xB8 : 0xC0, 0, 0);
    if (!bus.read_ack) {
        bus.addressed = 0;
    }
}

static avr_twi_t *find_twi(avr_t *a)
{
    avr_io_t *p;
    for (p = a->io_port; p; p = p->next) {
        if (p->kind && !strcmp(p->kind, "twi")) {
            return (avr_twi_t *)p;
        }
    }
    return NULL;
}

/* ---------------------------------------------------------------- UART <-> pty */
static struct {
    hp_decoder_t dec_host, dec_fw, dec_read;
    uint64_t host_frames_ok, host_bad, fw_states, fw_faults[16], fw_bad, fw_overrun;
    uint32_t fault_detail[16];
    uint8_t in_q[4096];
    size_t in_head, in_tail;
    int xon, await_host, host_present;
    uint32_t await_seq, read_force_seq;
    int read_force_valid, read_stop, read_other, compact;
    uint8_t out[64];
    size_t out_n;
    uint16_t fw_status;
    uint64_t tx_dropped, waits;
    uint64_t state_cyc, feed_at; /* lockstep --host-latency-us: the STATE's end, the feed */
} link_;

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

/* Whether the FORCE seq the host sent last answers the STATE awaited, or a later one: in
 * 32 bits, or in 16 bits in a compact session (PROTOCOL.md section 4). */
static int force_answers_await(void)
{
    if (link_.compact) {
        return (int16_t)(uint16_t)(link_.read_force_seq - link_.await_seq) >= 0;
    }
    return (int32_t)(link_.read_force_seq - link_.await_seq) >= 0;
}

static void on_fw_msg(const hp_msg_t *m)
{
    if (m->type == HP_MSG_STATE || m->type == HP_MSG_STATE_COMPACT) {
        int compact = m->type == HP_MSG_STATE_COMPACT;
        uint16_t st = compact ? m->u.state_compact.status : m->u.state.status;
        uint32_t seq = compact ? m->u.state_compact.seq : m->u.state.seq;
        link_.compact = compact;
        link_.fw_states++;
        link_.fw_status = st;
        budget.armed = (st & HP_STATUS_ARMED) != 0;
        if ((st & HP_STATUS_OVERRUN) && (st & HP_STATUS_ARMED)) {
            link_.fw_overrun++; /* armed ticks only (the first disarmed ones are no loop) */
        }
        if ((st & HP_STATUS_ARMED) && link_.host_present) {
            link_.await_host = 1;
            link_.await_seq = seq;
            link_.read_other = 0;
            link_.state_cyc = core[LEAD]->cycle;
        }
    } else if (m->type == HP_MSG_FAULT) {
        link_.fw_faults[m->u.fault.code & 15u]++;
        link_.fault_detail[m->u.fault.code & 15u] = m->u.fault.detail;
        budget.armed = 0;
    }
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
        flush_out();
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
        link_.xon = 1;
    }
}

static void uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    link_.xon = value ? 0 : 1;
}

static void on_host_msg(const hp_msg_t *m)
{
    link_.host_frames_ok++;
    last_fed_type = m->type;
    if (m->type == HP_MSG_HELLO_REQUEST) {
        ph.configs = 0;
    } else if (m->type == HP_MSG_CONFIG) {
        double rate = m->u.config.rate_hz;
        advance_to(core[LEAD]->cycle);
        budget.rate_hz = rate;
        if (rate > 0 && isfinite(rate)) {
            hand_on_config(rate);
        }
    } else if (m->type == HP_MSG_STOP) {
        advance_to(core[LEAD]->cycle);
        ph.held = 1; /* the hand holds the handle where it is */
        ph.qd[0] = ph.qd[1] = 0.0;
        ph.release_armed = 0;
    }
}

static void feed_uart(void)
{
    if (core[LEAD]->cycle < link_.feed_at) {
        return; /* lockstep --host-latency-us: the host's answer is not there yet */
    }
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

static void read_host(int timeout_ms)
{
    struct pollfd pfd = {master, POLLIN, 0};
    int r = poll(&pfd, 1, timeout_ms);
    link_.host_present = !(pfd.revents & POLLHUP);
    if (r > 0 && (pfd.revents & POLLIN)) {
        uint8_t buf[256];
        size_t room = (link_.in_tail + sizeof link_.in_q - link_.in_head - 1u) %
                      sizeof link_.in_q;
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

static uint64_t wall_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

/* Wait until the wall clock reads `target` [ns], taking the host's bytes as they come: a
 * wait on the pty (ppoll) until `target` less `spin` [ns], then a spin that checks the pty
 * without waiting. Each frame the host writes meanwhile is read and handed to the UART at
 * once (at the emulated cycle reached, which is at or after the wall time it came at). */
static void wait_until(uint64_t target, uint64_t spin)
{
    uint64_t t0 = wall_ns(), now = t0, spin_from = 0;
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
            read_host(0);
            feed_uart();
        }
        now = wall_ns();
    }
    tm.spin_ns += spin_from ? now - spin_from : 0;
    tm.sleep_ns += now - t0 - (spin_from ? now - spin_from : 0);
}

/* ---------------------------------------------------------------- report */

static void report(int code)
{
    FILE *f = opt.report ? fopen(opt.report, "w") : stdout;
    double period = budget.rate_hz > 0 ? F_CPU_HZ / budget.rate_hz : 0;
    double x[2] = {0, 0};
    int i;
    if (!f) {
        f = stdout;
    }
    five_bar(ph.q, x, NULL);
    fprintf(f, "{\"exit\": \"%s\", \"emulated_s\": %.9f, \"mode\": \"%s\",\n",
            code == 0 ? "ok" : "firmware stopped", (double)core[LEAD]->cycle / F_CPU_HZ,
            opt.realtime ? "realtime" : "lockstep");
    fprintf(f, " \"time\": {\"emulate_s\": %.6f, \"io_s\": %.6f, \"sleep_s\": %.6f, "
               "\"spin_s\": %.6f, \"spin_us\": %.1f, \"armed_mhz\": %.3f, \"slips\": %llu, "
               "\"slipped_s\": %.6f, \"behind_max_ms\": %.3f},\n",
            tm.emulate_ns * 1e-9, tm.io_ns * 1e-9, tm.sleep_ns * 1e-9, tm.spin_ns * 1e-9,
            opt.spin_us,
            tm.armed_emulate_ns ? tm.armed_cycles * 1e3 / (double)tm.armed_emulate_ns : 0.0,
            (unsigned long long)tm.slips, tm.slipped_ns * 1e-9, tm.behind_max_ns * 1e-6);
    fprintf(f, " \"budget\": {\"rate_hz\": %.6g, \"period_cycles\": %.0f, \"ticks\": %llu, "
               "\"leader_busy_mean_cycles\": %.1f, \"leader_busy_max_cycles\": %llu, "
               "\"follower_busy_mean_cycles\": %.1f, \"follower_busy_max_cycles\": %llu},\n",
            budget.rate_hz, period, (unsigned long long)budget.ticks,
            budget.ticks ? (double)budget.busy_sum[0] / (double)budget.ticks : 0.0,
            (unsigned long long)budget.busy_max[0],
            budget.ticks ? (double)budget.busy_sum[1] / (double)budget.ticks : 0.0,
            (unsigned long long)budget.busy_max[1]);
    fprintf(f, " \"twi\": {\"transactions\": %ld, \"nack_address\": %ld, \"nack_data\": %ld, "
               "\"bytes_written\": %ld, \"bytes_read\": %ld, \"stretched\": %ld, "
               "\"late_bytes\": %ld, \"overflow\": %ld, \"slack_ticks\": %llu, "
               "\"slack_min_cycles\": %llu, \"slack_mean_cycles\": %.1f, "
               "\"drive_max_cycles\": %llu},\n",
            bus.transactions, bus.nack_addr, bus.nack_data, bus.bytes_w, bus.bytes_r,
            bus.stretched, bus.late_bytes, bus.overflow, (unsigned long long)bus.slack_n,
            (unsigned long long)bus.slack_min,
            bus.slack_n ? (double)bus.slack_sum / (double)bus.slack_n : 0.0,
            (unsigned long long)bus.drive_max);
    fprintf(f, " \"host\": {\"frames_ok\": %llu, \"bad_frames\": %llu, \"waits\": %llu},\n",
            (unsigned long long)link_.host_frames_ok, (unsigned long long)link_.host_bad,
            (unsigned long long)link_.waits);
    fprintf(f, " \"firmware\": {\"states\": %llu, \"bad_frames\": %llu, \"overrun\": %llu, "
               "\"faults\": {",
            (unsigned long long)link_.fw_states, (unsigned long long)link_.fw_bad,
            (unsigned long long)link_.fw_overrun);
    {
        int first = 1;
        for (i = 0; i < 16; i++) {
            if (link_.fw_faults[i]) {
                fprintf(f, "%s\"%d\": {\"count\": %llu, \"detail\": %u}", first ? "" : ", ",
                        i, (unsigned long long)link_.fw_faults[i], link_.fault_detail[i]);
                first = 0;
            }
        }
    }
    fprintf(f, "}, \"tx_dropped\": %llu},\n", (unsigned long long)link_.tx_dropped);
    fprintf(f, " \"simavr\": {\"warnings\": %llu, \"last_warning\": \"",
            (unsigned long long)simlog.warnings);
    simlog_json(f);
    fprintf(f, "\"},\n");
    fprintf(f, " \"drive\": {\"leader_steps\": %d, \"follower_steps\": %d, "
               "\"torque_nm\": [%.9g, %.9g]},\n",
            (drive[LEAD].dir ? 1 : -1) * (int)drive[LEAD].n,
            (drive[FOLL].dir ? 1 : -1) * (int)drive[FOLL].n, ph.tau[0], ph.tau[1]);
    fprintf(f, " \"plant\": {\"q_rad\": [%.17g, %.17g], \"qd_rad_s\": [%.17g, %.17g], "
               "\"x_m\": [%.17g, %.17g], \"rk_steps\": %llu, \"bad_kinematics\": %llu, "
               "\"big_jumps\": %llu}}\n",
            ph.q[0], ph.q[1], ph.qd[0], ph.qd[1], x[0], x[1],
            (unsigned long long)ph.rk_steps, (unsigned long long)ph.bad_kinematics,
            (unsigned long long)ph.big_jumps);
    if (f != stdout) {
        fclose(f);
    }
}

/* ---------------------------------------------------------------- main */
static void on_signal(int s)
{
    stop_signal = s;
}

static void noop_sleep_l(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    slept[LEAD] += 1u + how_long;
}

static void noop_sleep_f(avr_t *a, avr_cycle_count_t how_long)
{
    (void)a;
    slept[FOLL] += 1u + how_long;
}

static avr_cycle_count_t fence_cb(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)when;
    (void)param;
    return 0;
}

static double num(const char *s, const char *name)
{
    return board_num(s, name, "pantograph_board");
}

static void nums(const char *s, const char *name, double *out, int n)
{
    char buf[512], *tok, *save = NULL;
    int i = 0;
    snprintf(buf, sizeof buf, "%s", s);
    for (tok = strtok_r(buf, ",", &save); tok; tok = strtok_r(NULL, ",", &save)) {
        if (i >= n) {
            break;
        }
        out[i++] = num(tok, name);
    }
    if (i != n) {
        fprintf(stderr, "pantograph_board: %s: %d numbers wanted: %s\n", name, n, s);
        exit(2);
    }
}

static void usage(void)
{
    fprintf(stderr,
            "usage: pantograph_board LEADER.elf FOLLOWER.elf [--geometry l1,l2,L1,L2,d]\n"
            "         [--home Q1,Q2] [--joint-inertia M11,M12,M21,M22]\n"
            "         [--joint-friction B11,B12,B21,B22] [--hand-mass KG] [--hand-damping NS_M]\n"
            "         [--amplitude M] [--substep S] [--nack-after N] [--duration S]\n"
            "         [--report FILE] [--link PATH] [--profile FILE] [--realtime]\n"
            "         [--spin-us US] [--host-latency-us US (lockstep)]\n"
            "       pantograph_board --plant-test [the plant's options] < 'tau1 tau2 dt' lines\n");
    exit(2);
}

/* --plant-test: from the home at rest, each stdin line "tau1 tau2 dt" holds the torques
 * [N m] over dt [s] and prints "q1 q2 qd1 qd2 x y" (%.17g). */
static int plant_test(void)
{
    double t1, t2, dt, x[2];
    ph.q[0] = opt.home[0];
    ph.q[1] = opt.home[1];
    while (scanf("%lf %lf %lf", &t1, &t2, &dt) == 3) {
        ph.tau[0] = t1;
        ph.tau[1] = t2;
        integrate(dt);
        five_bar(ph.q, x, NULL);
        printf("%.17g %.17g %.17g %.17g %.17g %.17g\n", ph.q[0], ph.q[1], ph.qd[0], ph.qd[1],
               x[0], x[1]);
    }
    return ph.bad_kinematics ? 1 : 0;
}

static void write_calibration(avr_t *a)
{
    pg_calib_t c;
    avr_eeprom_desc_t d;
    memset(&c, 0, sizeof c);
    c.magic = PG_CALIB_MAGIC;
    c.home_q1 = (float)opt.home[0];
    c.home_q2 = (float)opt.home[1];
    c.crc = hp_crc16(0xFFFFu, (const uint8_t *)&c, offsetof(pg_calib_t, crc));
    d.ee = (uint8_t *)&c;
    d.offset = 0;
    d.size = sizeof c;
    avr_ioctl(a, AVR_IOCTL_EEPROM_SET, &d);
}

int main(int argc, char **argv)
{
    elf_firmware_t fw[2];
    uint32_t flags = 0;
    int i, n_elf = 0, code = 0;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "--plant-test")) {
            opt.plant_test = 1;
            continue;
        }
        if (!strcmp(a, "--realtime")) {
            opt.realtime = 1;
            continue;
        }
        if (a[0] != '-') {
            if (n_elf >= 2) {
                usage();
            }
            opt.elf[n_elf++] = a;
            continue;
        }
        if (!v) {
            usage();
        }
        i++;
        if (!strcmp(a, "--geometry")) {
            double g[5];
            nums(v, a, g, 5);
            opt.l1 = g[0];
            opt.l2 = g[1];
            opt.L1 = g[2];
            opt.L2 = g[3];
            opt.d = g[4];
        } else if (!strcmp(a, "--home")) nums(v, a, opt.home, 2);
        else if (!strcmp(a, "--joint-inertia")) nums(v, a, opt.Mq, 4);
        else if (!strcmp(a, "--joint-friction")) nums(v, a, opt.Bq, 4);
        else if (!strcmp(a, "--hand-mass")) opt.mh = num(v, a);
        else if (!strcmp(a, "--hand-damping")) opt.bh = num(v, a);
        else if (!strcmp(a, "--amplitude")) opt.amplitude = num(v, a);
        else if (!strcmp(a, "--substep")) opt.substep = num(v, a);
        else if (!strcmp(a, "--nack-after")) opt.nack_after = (long)num(v, a);
        else if (!strcmp(a, "--duration")) opt.duration = num(v, a);
        else if (!strcmp(a, "--report")) opt.report = v;
        else if (!strcmp(a, "--link")) opt.link = v;
        else if (!strcmp(a, "--profile")) opt.profile = v;
        else if (!strcmp(a, "--spin-us")) opt.spin_us = num(v, a);
        else if (!strcmp(a, "--host-latency-us")) opt.host_latency_us = num(v, a);
        else usage();
    }
    if (!(opt.substep > 0) || !(opt.amplitude > 0) || !(opt.spin_us >= 0) ||
        opt.spin_us > 1e6 || !(opt.host_latency_us >= 0) || opt.host_latency_us > 1e6 ||
        (opt.realtime && opt.host_latency_us > 0)) {
        usage();
    }
    if (opt.plant_test) {
        return plant_test();
    }
    if (n_elf != 2) {
        usage();
    }
    avr_global_logger_set(log_stderr);
    for (i = 0; i < 2; i++) {
        memset(&fw[i], 0, sizeof fw[i]);
        if (elf_read_firmware(opt.elf[i], &fw[i])) {
            fprintf(stderr, "pantograph_board: cannot read %s\n", opt.elf[i]);
            return 2;
        }
        core[i] = avr_make_mcu_by_name("atmega328p");
        if (!core[i]) {
            fprintf(stderr, "pantograph_board: simavr has no atmega328p core\n");
            return 1;
        }
        avr_init(core[i]);
        core[i]->log = 0;
        avr_load_firmware(core[i], &fw[i]);
        core[i]->frequency = (uint32_t)F_CPU_HZ;
        core[i]->vcc = core[i]->avcc = core[i]->aref = HK_ADC_VREF_MV;
        core[i]->sleep = i == LEAD ? noop_sleep_l : noop_sleep_f;
        twi[i] = find_twi(core[i]);
        adc_irq[i] = avr_io_getirq(core[i], AVR_IOCTL_ADC_GETIRQ, 0);
        avr_irq_register_notify(adc_irq[i] + ADC_IRQ_OUT_TRIGGER, adc_trigger,
                                (void *)(intptr_t)i);
    }
    if (!twi[LEAD] || !twi[FOLL]) {
        fprintf(stderr, "pantograph_board: simavr's atmega328p has no TWI\n");
        return 1;
    }
    write_calibration(core[LEAD]);
    avr_irq_register_notify(twi[LEAD]->io.irq + TWI_IRQ_OUTPUT, leader_twi_out, NULL);
    avr_register_io_write(core[FOLL], R_TWCR, follower_twcr, NULL);
    ph.q[0] = opt.home[0];
    ph.q[1] = opt.home[1];
    ph.held = 1;
    hp_decoder_init(&link_.dec_host);
    hp_decoder_init(&link_.dec_read);
    hp_decoder_init(&link_.dec_fw);
    uart_irq = avr_io_getirq(core[LEAD], AVR_IOCTL_UART_GETIRQ('0'), 0);
    avr_ioctl(core[LEAD], AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(core[LEAD], AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUTPUT, uart_out, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XON, uart_xon, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XOFF, uart_xoff, NULL);
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    signal(SIGPIPE, SIG_IGN);
    master = board_open_pty(opt.link, "pantograph_board");
    while (!stop_signal) {
        uint64_t end = core[LEAD]->cycle + (win.open ? WINDOW_CHUNK : 1600u); /* 100 us */
        if (link_.feed_at > core[LEAD]->cycle && link_.feed_at < end) {
            end = link_.feed_at; /* the host's delayed answer is fed at its cycle */
        }
        uint64_t t_a = wall_ns(), c_a = core[LEAD]->cycle, t_b;
        int pace;
        if (opt.duration > 0 && (double)core[LEAD]->cycle >= opt.duration * F_CPU_HZ) {
            break;
        }
        while (core[LEAD]->cycle < end && !link_.await_host) {
            /* the follower never ahead of the leader (the bus events the leader causes
             * are due in the follower's future), the leader at most FENCE cycles ahead of
             * the follower */
            int c = core[LEAD]->cycle < core[FOLL]->cycle + FENCE ? LEAD : FOLL;
            avr_t *a = core[c], *o = core[1 - c];
            uint64_t c0 = a->cycle, s0 = slept[c];
            uint32_t pc0 = a->pc;
            uint64_t limit = c == LEAD ? o->cycle + FENCE : o->cycle;
            int st;
            if (limit > a->cycle) {
                avr_cycle_timer_register(a, limit - a->cycle, fence_cb, NULL);
            }
            st = avr_run(a);
            if (st == cpu_Done || st == cpu_Crashed) {
                fprintf(stderr, "pantograph_board: %s firmware stopped (state %d) at "
                                "%.6f s\n", c == LEAD ? "leader" : "follower", st,
                        (double)a->cycle / F_CPU_HZ);
                code = 1;
                goto done;
            }
            {
                uint64_t busy = (a->cycle - c0) - (slept[c] - s0);
                budget.window_busy[c] += busy;
                if (opt.profile && c == LEAD && budget.armed && busy) {
                    prof[(pc0 >> 1) % 16384u] += busy;
                }
            }
            sample_drive(c);
            if (c == FOLL) {
                bus_pump();
            }
        }
        t_b = wall_ns();
        tm.emulate_ns += t_b - t_a;
        if (budget.armed) {
            tm.armed_emulate_ns += t_b - t_a;
            tm.armed_cycles += core[LEAD]->cycle - c_a;
        }
        flush_out();
        read_host(0);
        if (opt.realtime) {
            if (link_.await_host && opt.spin_us > 0) {
                win.open = 1; /* an armed STATE is out: watch for its FORCE (see win) */
                win.since = wall_ns();
            }
            if (win.open && ((link_.read_force_valid && force_answers_await()) ||
                             link_.read_stop || !link_.host_present ||
                             (double)(wall_ns() - win.since) > opt.spin_us * 1e3)) {
                win.open = 0;
            }
        } else if (link_.await_host) {
            /* lockstep: wait (wall time) for the host's FORCE answering this STATE */
            link_.waits++;
            while (!(link_.read_force_valid && force_answers_await()) &&
                   !link_.read_stop && !link_.read_other && link_.host_present &&
                   !stop_signal) {
                read_host(100);
            }
            if (opt.host_latency_us > 0) {
                /* the host answers host_latency_us after the STATE's last byte */
                link_.feed_at = link_.state_cyc +
                                (uint64_t)(opt.host_latency_us * F_CPU_HZ * 1e-6 + 0.5);
            }
        }
        link_.await_host = 0;
        feed_uart();
        tm.io_ns += wall_ns() - t_b;
        /* real time: always with --realtime; in lockstep while a host listens to a
         * disarmed device (its STATEs would flood the host as fast as the host reads) */
        pace = opt.realtime || (link_.host_present && !budget.armed);
        if (pace) {
            uint64_t emu = (uint64_t)((double)core[LEAD]->cycle * 1e9 / F_CPU_HZ);
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
    if (opt.profile) {
        FILE *pf = fopen(opt.profile, "w");
        unsigned w;
        for (w = 0; pf && w < 16384u; w++) {
            if (prof[w]) {
                fprintf(pf, "%#x %llu\n", 2u * w, (unsigned long long)prof[w]);
            }
        }
        if (pf) {
            fclose(pf);
        }
    }
    return code;
}
