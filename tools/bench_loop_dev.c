/* The device side and the floor host of tools/bench_loop.py (compiled by it with cc).
 *
 * device MASTER_FD RATE_HZ N RTT_FILE MODE
 *   A device on a pty master speaking the hapsim protocol (firmware_protocol/PROTOCOL.md):
 *   MODE "proto" answers HELLO_REQUEST (HELLO) and PING (PONG) and starts ticking at
 *   CONFIG; MODE "raw" starts at once. Each tick k (absolute deadlines, clock_nanosleep
 *   TIMER_ABSTIME) sends STATE k (armed, force applied, force_seq = newest FORCE seq in)
 *   with a constant position; between ticks it waits in ppoll and timestamps every frame
 *   that comes back with seq j (a FORCE, or the floor's echo of STATE j): round trip
 *   [us] = arrival - send of STATE j, written as float64 to RTT_FILE (NaN: no answer).
 *   A tick k > 0 at which no answer to k - 1 is in is late (the device holds an older
 *   force). Prints "late N answered M" on stdout. Stops after N ticks or at STOP.
 *
 * echo SLAVE_PATH N TURN_FILE
 *   The floor host: raw slave, read -> write the same bytes back, no decoding; the
 *   turnaround [us] of each read (read returned -> write returned) to TURN_FILE.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

static int64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000LL + t.tv_nsec;
}

static uint16_t crc16(const uint8_t *p, int n) {      /* CCITT-FALSE */
    uint16_t c = 0xFFFF;
    for (int i = 0; i < n; i++) {
        c ^= (uint16_t)p[i] << 8;
        for (int b = 0; b < 8; b++) c = (c & 0x8000) ? (uint16_t)((c << 1) ^ 0x1021) : (uint16_t)(c << 1);
    }
    return c;
}

static int cobs_encode(const uint8_t *in, int n, uint8_t *out) {
    int code_at = 0, o = 1;
    uint8_t code = 1;
    for (int i = 0; i < n; i++) {
        if (in[i] == 0) { out[code_at] = code; code_at = o++; code = 1; }
        else { out[o++] = in[i]; if (++code == 0xFF) { out[code_at] = code; code_at = o++; code = 1; } }
    }
    out[code_at] = code;
    out[o++] = 0;
    return o;
}

static int cobs_decode(const uint8_t *in, int n, uint8_t *out) {
    int i = 0, o = 0;
    while (i < n) {
        int code = in[i++];
        if (code == 0 || i + code - 1 > n) return -1;
        for (int j = 1; j < code; j++) out[o++] = in[i++];
        if (code < 0xFF && i < n) out[o++] = 0;
    }
    return o;
}

static int fd_g;

static void send_packet(uint8_t *pkt, int n) {
    uint16_t c = crc16(pkt, n);
    pkt[n] = c >> 8;
    pkt[n + 1] = c & 0xFF;
    uint8_t fr[300];
    int m = cobs_encode(pkt, n + 2, fr);
    int done = 0;
    while (done < m) {
        ssize_t w = write(fd_g, fr + done, m - done);
        if (w > 0) done += (int)w;
        else if (errno != EAGAIN && errno != EINTR) return;
    }
}

static int device(int argc, char **argv) {
    if (argc < 7) return 2;
    fd_g = atoi(argv[2]);
    double rate = atof(argv[3]);
    long n = atol(argv[4]);
    const char *rtt_path = argv[5];
    int proto = strcmp(argv[6], "proto") == 0;
    int64_t period = (int64_t)llround(1e9 / rate);
    int64_t *sent = calloc(n, sizeof(int64_t));
    double *rtt = malloc(n * sizeof(double));
    for (long k = 0; k < n; k++) rtt[k] = NAN;
    uint8_t rb[65536], fr[300], pkt[300];
    int nrb = 0, started = !proto, stop = 0;
    long k = 0, late = 0, answered = 0;
    int64_t newest = -1;
    int64_t deadline = now_ns() + 20 * period;
    int64_t give_up = now_ns() + 60000000000LL;
    while (!stop && k < n) {
        int64_t now = now_ns();
        if (started && now >= deadline) {
            if (k > 0 && isnan(rtt[k - 1])) late++;
            pkt[0] = 0x10;
            uint32_t s = (uint32_t)k; memcpy(pkt + 1, &s, 4);
            uint64_t t_us = (uint64_t)(now / 1000); memcpy(pkt + 5, &t_us, 8);
            uint16_t st = 0x0001 | (newest >= 0 ? 0x0080 : 0); memcpy(pkt + 13, &st, 2);
            uint32_t fs = (uint32_t)(newest >= 0 ? newest : 0); memcpy(pkt + 15, &fs, 4);
            double x = 0.001; memcpy(pkt + 19, &x, 8);
            sent[k] = now_ns();
            send_packet(pkt, 27);
            k++;
            deadline += period;
            if (now - deadline > period) deadline = now + period;   /* slip, as the mock */
            continue;
        }
        if (!started && now > give_up) break;
        int64_t wait = started ? deadline - now : 10000000;
        struct timespec ts = {wait / 1000000000LL, wait % 1000000000LL};
        struct pollfd p = {fd_g, POLLIN, 0};
        int r = ppoll(&p, 1, &ts, NULL);
        if (r <= 0) continue;
        ssize_t got = read(fd_g, rb + nrb, sizeof rb - nrb);
        int64_t t_in = now_ns();
        if (got <= 0) { if (errno == EAGAIN || errno == EINTR) continue; break; }
        nrb += (int)got;
        int a = 0;
        for (int z = 0; z < nrb; z++) {
            if (rb[z] != 0) continue;
            int len = z - a;
            if (len > 0 && len < 280) {
                memcpy(fr, rb + a, len);
                int m = cobs_decode(fr, len, pkt);
                if (m >= 3 && crc16(pkt, m) == 0) {
                    uint8_t ty = pkt[0];
                    if ((ty == 0x11 || ty == 0x10) && m >= 7 && started) {
                        uint32_t s; memcpy(&s, pkt + 1, 4);
                        if (s < (uint32_t)k && isnan(rtt[s])) {
                            rtt[s] = (t_in - sent[s]) * 1e-3;
                            answered++;
                        }
                        if ((int64_t)s > newest) newest = s;
                    } else if (ty == 0x02) {               /* HELLO_REQUEST -> HELLO */
                        uint8_t h[64] = {0x01, 1, 1};
                        uint32_t id = 13; memcpy(h + 3, &id, 4);
                        double v[4] = {1e-6, 1e-3, 10.0, rate}; memcpy(h + 7, v, 32);
                        send_packet(h, 39);
                    } else if (ty == 0x20 && m == 15) {    /* PING -> PONG */
                        uint8_t q[64] = {0x21};
                        memcpy(q + 1, pkt + 1, 12);
                        uint64_t dt = (uint64_t)(now_ns() / 1000); memcpy(q + 13, &dt, 8);
                        send_packet(q, 21);
                    } else if (ty == 0x03) {               /* CONFIG: tick */
                        if (!started) { started = 1; deadline = now_ns() + period; }
                    } else if (ty == 0x31) {
                        stop = 1;
                    }
                }
            }
            a = z + 1;
        }
        memmove(rb, rb + a, nrb - a);
        nrb -= a;
    }
    FILE *f = fopen(rtt_path, "wb");
    if (f) { fwrite(rtt, sizeof(double), k, f); fclose(f); }
    printf("late %ld answered %ld ticks %ld\n", late, answered, k);
    return 0;
}

static int echo(int argc, char **argv) {
    if (argc < 5) return 2;
    int fd = open(argv[2], O_RDWR | O_NOCTTY);
    if (fd < 0) return 1;
    struct termios t;
    tcgetattr(fd, &t);
    cfmakeraw(&t);
    tcsetattr(fd, TCSANOW, &t);
    long n = atol(argv[3]);
    double *turn = malloc((n + 16) * sizeof(double));
    long m = 0;
    uint8_t buf[65536];
    printf("ready\n");
    fflush(stdout);
    while (m < n) {
        ssize_t r = read(fd, buf, sizeof buf);
        int64_t t0 = now_ns();
        if (r <= 0) { if (r < 0 && errno == EINTR) continue; break; }
        ssize_t done = 0;
        while (done < r) { ssize_t w = write(fd, buf + done, r - done); if (w <= 0) break; done += w; }
        turn[m++] = (now_ns() - t0) * 1e-3;
    }
    FILE *f = fopen(argv[4], "wb");
    if (f) { fwrite(turn, sizeof(double), m, f); fclose(f); }
    return 0;
}

int main(int argc, char **argv) {
    if (argc > 1 && strcmp(argv[1], "device") == 0) return device(argc, argv);
    if (argc > 1 && strcmp(argv[1], "echo") == 0) return echo(argc, argv);
    fprintf(stderr, "usage: device MASTER_FD RATE N RTT_FILE proto|raw | echo SLAVE N TURN_FILE\n");
    return 2;
}
