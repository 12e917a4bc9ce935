/*
 * hproto_driver.c -- line-oriented driver of firmware_protocol/c/hproto.c for the Python
 * test suite (tests/test_protocol_c.py compiles it with -I firmware_protocol/c). Not part of
 * the reference implementation: it uses stdio and stdlib, which the library must not.
 *
 * Commands on stdin, one per line; one or more JSON lines on stdout per command:
 *   D <hex>          decode one frame          -> message JSON or {"error": "..."}
 *   S <hex>          feed bytes to the stream decoder (kept across S lines)
 *                    -> one JSON line per frame ended (message or error), then
 *                       {"stats": {...}, "buffered": n}
 *   I                reset the stream decoder
 *   L <limit> <f>... hp_limit_force on the doubles -> {"status": s, "force": [...]}
 *   W <last> <now> <timeout>  hp_watchdog_expired -> {"expired": 0|1}
 *   C <now> <low>    hp_compact_seq -> {"seq": n}
 *   E <type> <v>...  encode a message: type id in decimal, then the fields in wire order,
 *                    integers in decimal, doubles as 0x + 16 hex digits of their bits
 *                    -> {"frame": "<hex>"} or {"error": "encode"}
 * Doubles are printed as "0x" + 16 hex digits of their IEEE-754 bits (exact, NaN-safe);
 * the binary32 values of the compact messages as "0x" + 8 hex digits, in and out.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "hproto.h"

#define LINE_MAX_LEN 65536

static char line[LINE_MAX_LEN];
static uint8_t bytes[LINE_MAX_LEN / 2];

static size_t parse_hex(const char *s, uint8_t *out)
{
    size_t n = 0;
    while (s[0] && s[1] && s[0] != '\n') {
        char tmp[3];
        tmp[0] = s[0];
        tmp[1] = s[1];
        tmp[2] = 0;
        out[n++] = (uint8_t)strtoul(tmp, NULL, 16);
        s += 2;
    }
    return n;
}

static void print_f64(double v)
{
    uint64_t bits;
    memcpy(&bits, &v, sizeof bits);
    printf("\"0x%016llx\"", (unsigned long long)bits);
}

static void print_f64s(const double *v, unsigned n)
{
    unsigned i;
    printf("[");
    for (i = 0; i < n; i++) {
        if (i) {
            printf(", ");
        }
        print_f64(v[i]);
    }
    printf("]");
}

static void print_f32s(const uint32_t *v, unsigned n)
{
    unsigned i;
    printf("[");
    for (i = 0; i < n; i++) {
        printf("%s\"0x%08lx\"", i ? ", " : "", (unsigned long)v[i]);
    }
    printf("]");
}

/* Remaining binary32 patterns on the line (0x + 8 hex digits), at most HP_MAX_AXES + 1. */
static uint8_t next_f32s(char **s, uint32_t *out)
{
    uint8_t n = 0;
    for (;;) {
        char *end;
        unsigned long bits;
        while (**s == ' ') {
            (*s)++;
        }
        if (**s == 0 || **s == '\n' || n > HP_MAX_AXES) {
            return n;
        }
        bits = strtoul(*s, &end, 16);
        if (end == *s) {
            return n;
        }
        *s = end;
        if (n < HP_MAX_AXES) {
            out[n] = (uint32_t)bits;
        }
        n++;
    }
}

static const char *error_name(int r)
{
    switch (r) {
    case HP_ERR_BAD_COBS: return "bad_cobs";
    case HP_ERR_BAD_CRC: return "bad_crc";
    case HP_ERR_OVERLONG: return "overlong";
    case HP_ERR_UNKNOWN_TYPE: return "unknown_type";
    case HP_ERR_MALFORMED: return "malformed";
    default: return "?";
    }
}

static void print_msg(int r, const hp_msg_t *m)
{
    if (r != HP_OK) {
        printf("{\"error\": \"%s\"}\n", error_name(r));
        return;
    }
    switch (m->type) {
    case HP_MSG_HELLO:
        printf("{\"type\": \"HELLO\", \"protocol_version\": %u, \"n_axes\": %u, "
               "\"device_id\": %lu, \"position_scale\": ",
               m->u.hello.protocol_version, m->u.hello.n_axes,
               (unsigned long)m->u.hello.device_id);
        print_f64(m->u.hello.position_scale);
        printf(", \"force_scale\": ");
        print_f64(m->u.hello.force_scale);
        printf(", \"force_limit\": ");
        print_f64(m->u.hello.force_limit);
        printf(", \"native_rate_hz\": ");
        print_f64(m->u.hello.native_rate_hz);
        printf("}\n");
        break;
    case HP_MSG_HELLO_REQUEST:
        printf("{\"type\": \"HELLO_REQUEST\", \"protocol_version\": %u}\n",
               m->u.hello_request.protocol_version);
        break;
    case HP_MSG_CONFIG:
        printf("{\"type\": \"CONFIG\", \"rate_hz\": ");
        print_f64(m->u.config.rate_hz);
        printf(", \"watchdog_us\": %lu, \"force_limit\": ",
               (unsigned long)m->u.config.watchdog_us);
        print_f64(m->u.config.force_limit);
        printf("}\n");
        break;
    case HP_MSG_LINK:
        printf("{\"type\": \"LINK\", \"baud\": %lu, \"bits_per_byte\": %u}\n",
               (unsigned long)m->u.link.baud, m->u.link.bits_per_byte);
        break;
    case HP_MSG_SENSORS_REQUEST:
        printf("{\"type\": \"SENSORS_REQUEST\", \"sensors\": %u}\n",
               (unsigned)m->u.sensors_request.sensors);
        break;
    case HP_MSG_SENSORS:
        printf("{\"type\": \"SENSORS\", \"offered\": %u, \"enabled\": %u}\n",
               (unsigned)m->u.sensors.offered, (unsigned)m->u.sensors.enabled);
        break;
    case HP_MSG_VELOCITY:
        printf("{\"type\": \"VELOCITY\", \"seq\": %lu, \"velocity\": ",
               (unsigned long)m->u.velocity.seq);
        print_f64s(m->u.velocity.velocity, m->u.velocity.n_axes);
        printf("}\n");
        break;
    case HP_MSG_STATE:
        printf("{\"type\": \"STATE\", \"seq\": %lu, \"time_us\": %llu, \"status\": %u, "
               "\"force_seq\": %lu, \"position\": ",
               (unsigned long)m->u.state.seq, (unsigned long long)m->u.state.time_us,
               (unsigned)m->u.state.status, (unsigned long)m->u.state.force_seq);
        print_f64s(m->u.state.position, m->u.state.n_axes);
        printf("}\n");
        break;
    case HP_MSG_FORCE:
        printf("{\"type\": \"FORCE\", \"seq\": %lu, \"force\": ", (unsigned long)m->u.force.seq);
        print_f64s(m->u.force.force, m->u.force.n_axes);
        printf("}\n");
        break;
    case HP_MSG_STATE_COMPACT:
        printf("{\"type\": \"STATE_COMPACT\", \"seq\": %u, \"status\": %u, \"lag\": %u, "
               "\"position\": ", (unsigned)m->u.state_compact.seq,
               (unsigned)m->u.state_compact.status, (unsigned)m->u.state_compact.lag);
        print_f32s(m->u.state_compact.position, m->u.state_compact.n_axes);
        printf("}\n");
        break;
    case HP_MSG_FORCE_COMPACT:
        printf("{\"type\": \"FORCE_COMPACT\", \"seq\": %u, \"force\": ",
               (unsigned)m->u.force_compact.seq);
        print_f32s(m->u.force_compact.force, m->u.force_compact.n_axes);
        printf("}\n");
        break;
    case HP_MSG_PING:
        printf("{\"type\": \"PING\", \"nonce\": %lu, \"host_time_us\": %llu}\n",
               (unsigned long)m->u.ping.nonce, (unsigned long long)m->u.ping.host_time_us);
        break;
    case HP_MSG_PONG:
        printf("{\"type\": \"PONG\", \"nonce\": %lu, \"host_time_us\": %llu, "
               "\"device_time_us\": %llu}\n",
               (unsigned long)m->u.pong.nonce, (unsigned long long)m->u.pong.host_time_us,
               (unsigned long long)m->u.pong.device_time_us);
        break;
    case HP_MSG_FAULT:
        printf("{\"type\": \"FAULT\", \"code\": %u, \"detail\": %lu}\n",
               (unsigned)m->u.fault.code, (unsigned long)m->u.fault.detail);
        break;
    case HP_MSG_STOP:
        printf("{\"type\": \"STOP\"}\n");
        break;
    default:
        printf("{\"error\": \"bug\"}\n");
        break;
    }
}

static unsigned long long next_u(char **s)
{
    return strtoull(*s, s, 0);
}

static double next_f(char **s)
{
    uint64_t bits = (uint64_t)strtoull(*s, s, 16);
    double v;
    memcpy(&v, &bits, sizeof v);
    return v;
}

/* Remaining doubles on the line, at most HP_MAX_AXES + 1 (to test the limit). */
static uint8_t next_fs(char **s, double *out)
{
    uint8_t n = 0;
    for (;;) {
        char *end;
        uint64_t bits;
        while (**s == ' ') {
            (*s)++;
        }
        if (**s == 0 || **s == '\n' || n > HP_MAX_AXES) {
            return n;
        }
        bits = (uint64_t)strtoull(*s, &end, 16);
        if (end == *s) {
            return n;
        }
        *s = end;
        if (n < HP_MAX_AXES) {
            memcpy(&out[n], &bits, sizeof bits);
        }
        n++;
    }
}

static void do_encode(char *s)
{
    hp_msg_t m;
    uint8_t out[HP_MAX_FRAME];
    size_t n, i;
    memset(&m, 0, sizeof m);
    m.type = (uint8_t)next_u(&s);
    switch (m.type) {
    case HP_MSG_HELLO:
        m.u.hello.protocol_version = (uint8_t)next_u(&s);
        m.u.hello.n_axes = (uint8_t)next_u(&s);
        m.u.hello.device_id = (uint32_t)next_u(&s);
        m.u.hello.position_scale = next_f(&s);
        m.u.hello.force_scale = next_f(&s);
        m.u.hello.force_limit = next_f(&s);
        m.u.hello.native_rate_hz = next_f(&s);
        break;
    case HP_MSG_HELLO_REQUEST:
        m.u.hello_request.protocol_version = (uint8_t)next_u(&s);
        break;
    case HP_MSG_CONFIG:
        m.u.config.rate_hz = next_f(&s);
        m.u.config.watchdog_us = (uint32_t)next_u(&s);
        m.u.config.force_limit = next_f(&s);
        break;
    case HP_MSG_LINK:
        m.u.link.baud = (uint32_t)next_u(&s);
        m.u.link.bits_per_byte = (uint8_t)next_u(&s);
        break;
    case HP_MSG_SENSORS_REQUEST:
        m.u.sensors_request.sensors = (uint16_t)next_u(&s);
        break;
    case HP_MSG_SENSORS:
        m.u.sensors.offered = (uint16_t)next_u(&s);
        m.u.sensors.enabled = (uint16_t)next_u(&s);
        break;
    case HP_MSG_VELOCITY:
        m.u.velocity.seq = (uint32_t)next_u(&s);
        m.u.velocity.n_axes = next_fs(&s, m.u.velocity.velocity);
        break;
    case HP_MSG_STATE:
        m.u.state.seq = (uint32_t)next_u(&s);
        m.u.state.time_us = (uint64_t)next_u(&s);
        m.u.state.status = (uint16_t)next_u(&s);
        m.u.state.force_seq = (uint32_t)next_u(&s);
        m.u.state.n_axes = next_fs(&s, m.u.state.position);
        break;
    case HP_MSG_FORCE:
        m.u.force.seq = (uint32_t)next_u(&s);
        m.u.force.n_axes = next_fs(&s, m.u.force.force);
        break;
    case HP_MSG_STATE_COMPACT:
        m.u.state_compact.seq = (uint16_t)next_u(&s);
        m.u.state_compact.status = (uint8_t)next_u(&s);
        m.u.state_compact.lag = (uint8_t)next_u(&s);
        m.u.state_compact.n_axes = next_f32s(&s, m.u.state_compact.position);
        break;
    case HP_MSG_FORCE_COMPACT:
        m.u.force_compact.seq = (uint16_t)next_u(&s);
        m.u.force_compact.n_axes = next_f32s(&s, m.u.force_compact.force);
        break;
    case HP_MSG_PING:
        m.u.ping.nonce = (uint32_t)next_u(&s);
        m.u.ping.host_time_us = (uint64_t)next_u(&s);
        break;
    case HP_MSG_PONG:
        m.u.pong.nonce = (uint32_t)next_u(&s);
        m.u.pong.host_time_us = (uint64_t)next_u(&s);
        m.u.pong.device_time_us = (uint64_t)next_u(&s);
        break;
    case HP_MSG_FAULT:
        m.u.fault.code = (uint16_t)next_u(&s);
        m.u.fault.detail = (uint32_t)next_u(&s);
        break;
    default:
        break;
    }
    n = hp_encode(&m, out, sizeof out);
    if (n == 0) {
        printf("{\"error\": \"encode\"}\n");
        return;
    }
    printf("{\"frame\": \"");
    for (i = 0; i < n; i++) {
        printf("%02x", out[i]);
    }
    printf("\"}\n");
}

int main(void)
{
    static hp_decoder_t dec;
    hp_msg_t m;
    hp_decoder_init(&dec);
    while (fgets(line, sizeof line, stdin)) {
        size_t n, i;
        switch (line[0]) {
        case 'D':
            n = parse_hex(line + 2, bytes);
            print_msg(hp_decode_frame(bytes, n, &m), &m);
            break;
        case 'S':
            n = parse_hex(line + 2, bytes);
            for (i = 0; i < n; i++) {
                int r = hp_decoder_feed(&dec, bytes[i], &m);
                if (r != HP_NONE) {
                    print_msg(r, &m);
                }
            }
            printf("{\"stats\": {\"frames_ok\": %lu, \"bad_cobs\": %lu, \"bad_crc\": %lu, "
                   "\"overlong\": %lu, \"unknown_type\": %lu, \"malformed\": %lu}, "
                   "\"buffered\": %lu}\n",
                   (unsigned long)dec.frames_ok, (unsigned long)dec.bad_cobs,
                   (unsigned long)dec.bad_crc, (unsigned long)dec.overlong,
                   (unsigned long)dec.unknown_type, (unsigned long)dec.malformed,
                   (unsigned long)dec.len);
            break;
        case 'I':
            hp_decoder_init(&dec);
            printf("{\"reset\": true}\n");
            break;
        case 'E':
            do_encode(line + 2);
            break;
        case 'L': {
            char *s = line + 2;
            double lim = next_f(&s), f[HP_MAX_AXES];
            uint8_t k = next_fs(&s, f);
            unsigned st;
            if (k > HP_MAX_AXES) {
                k = HP_MAX_AXES;
            }
            st = hp_limit_force(f, k, lim);
            printf("{\"status\": %u, \"force\": ", st);
            print_f64s(f, k);
            printf("}\n");
            break;
        }
        case 'C': {
            char *s = line + 2;
            unsigned long long now = next_u(&s), low = next_u(&s);
            printf("{\"seq\": %lu}\n",
                   (unsigned long)hp_compact_seq((uint32_t)now, (uint16_t)low));
            break;
        }
        case 'W': {
            char *s = line + 2;
            unsigned long long last = next_u(&s), now = next_u(&s), to = next_u(&s);
            printf("{\"expired\": %d}\n",
                   hp_watchdog_expired((uint64_t)last, (uint64_t)now, (uint32_t)to));
            break;
        }
        default:
            printf("{\"error\": \"command\"}\n");
            break;
        }
        fflush(stdout);
    }
    return 0;
}
