/*
 * hproto.c -- reference C99 implementation of the hapsim framed serial protocol.
 * See hproto.h for the API and ../PROTOCOL.md for the specification.
 */
#include "hproto.h"

#include <string.h>

/* The wire carries IEEE-754 binary64: as `double` where it is 64-bit, else as bit patterns. */
#ifndef HP_F64_AS_BITS
typedef char hp_assert_double_is_64_bits[(sizeof(double) == 8) ? 1 : -1];
#endif

#define HP_STATE_FIXED 19u /* type + seq + time_us + status + force_seq */
#define HP_FORCE_FIXED 5u  /* type + seq */
#define HP_STATE_C_FIXED 5u /* type + seq16 + status8 + lag8 */
#define HP_FORCE_C_FIXED 3u /* type + seq16 */

/* ------------------------------------------------------------------ CRC */

/* CRC of each value of the register's top byte: crc_table[x] = x * 2^8 reduced by the
 * polynomial 0x1021 (the bit loop run 8 times on x << 8). A firmware may keep it in flash:
 * it defines HP_ROM (the attribute) and HP_ROM_U16(p) (the read), as the Hapkit build does
 * with -include hp_rom.h (avr-libc's PROGMEM and pgm_read_word): 512 B of flash, about
 * half the cycles per byte of the shift-and-xor form (31 cycles on the ATmega328P). */
#ifndef HP_ROM
#define HP_ROM
#define HP_ROM_U16(p) (*(p))
#endif
static const uint16_t crc_table[256] HP_ROM = {
    0x0000u, 0x1021u, 0x2042u, 0x3063u, 0x4084u, 0x50A5u, 0x60C6u, 0x70E7u,
    0x8108u, 0x9129u, 0xA14Au, 0xB16Bu, 0xC18Cu, 0xD1ADu, 0xE1CEu, 0xF1EFu,
    0x1231u, 0x0210u, 0x3273u, 0x2252u, 0x52B5u, 0x4294u, 0x72F7u, 0x62D6u,
    0x9339u, 0x8318u, 0xB37Bu, 0xA35Au, 0xD3BDu, 0xC39Cu, 0xF3FFu, 0xE3DEu,
    0x2462u, 0x3443u, 0x0420u, 0x1401u, 0x64E6u, 0x74C7u, 0x44A4u, 0x5485u,
    0xA56Au, 0xB54Bu, 0x8528u, 0x9509u, 0xE5EEu, 0xF5CFu, 0xC5ACu, 0xD58Du,
    0x3653u, 0x2672u, 0x1611u, 0x0630u, 0x76D7u, 0x66F6u, 0x5695u, 0x46B4u,
    0xB75Bu, 0xA77Au, 0x9719u, 0x8738u, 0xF7DFu, 0xE7FEu, 0xD79Du, 0xC7BCu,
    0x48C4u, 0x58E5u, 0x6886u, 0x78A7u, 0x0840u, 0x1861u, 0x2802u, 0x3823u,
    0xC9CCu, 0xD9EDu, 0xE98Eu, 0xF9AFu, 0x8948u, 0x9969u, 0xA90Au, 0xB92Bu,
    0x5AF5u, 0x4AD4u, 0x7AB7u, 0x6A96u, 0x1A71u, 0x0A50u, 0x3A33u, 0x2A12u,
    0xDBFDu, 0xCBDCu, 0xFBBFu, 0xEB9Eu, 0x9B79u, 0x8B58u, 0xBB3Bu, 0xAB1Au,
    0x6CA6u, 0x7C87u, 0x4CE4u, 0x5CC5u, 0x2C22u, 0x3C03u, 0x0C60u, 0x1C41u,
    0xEDAEu, 0xFD8Fu, 0xCDECu, 0xDDCDu, 0xAD2Au, 0xBD0Bu, 0x8D68u, 0x9D49u,
    0x7E97u, 0x6EB6u, 0x5ED5u, 0x4EF4u, 0x3E13u, 0x2E32u, 0x1E51u, 0x0E70u,
    0xFF9Fu, 0xEFBEu, 0xDFDDu, 0xCFFCu, 0xBF1Bu, 0xAF3Au, 0x9F59u, 0x8F78u,
    0x9188u, 0x81A9u, 0xB1CAu, 0xA1EBu, 0xD10Cu, 0xC12Du, 0xF14Eu, 0xE16Fu,
    0x1080u, 0x00A1u, 0x30C2u, 0x20E3u, 0x5004u, 0x4025u, 0x7046u, 0x6067u,
    0x83B9u, 0x9398u, 0xA3FBu, 0xB3DAu, 0xC33Du, 0xD31Cu, 0xE37Fu, 0xF35Eu,
    0x02B1u, 0x1290u, 0x22F3u, 0x32D2u, 0x4235u, 0x5214u, 0x6277u, 0x7256u,
    0xB5EAu, 0xA5CBu, 0x95A8u, 0x8589u, 0xF56Eu, 0xE54Fu, 0xD52Cu, 0xC50Du,
    0x34E2u, 0x24C3u, 0x14A0u, 0x0481u, 0x7466u, 0x6447u, 0x5424u, 0x4405u,
    0xA7DBu, 0xB7FAu, 0x8799u, 0x97B8u, 0xE75Fu, 0xF77Eu, 0xC71Du, 0xD73Cu,
    0x26D3u, 0x36F2u, 0x0691u, 0x16B0u, 0x6657u, 0x7676u, 0x4615u, 0x5634u,
    0xD94Cu, 0xC96Du, 0xF90Eu, 0xE92Fu, 0x99C8u, 0x89E9u, 0xB98Au, 0xA9ABu,
    0x5844u, 0x4865u, 0x7806u, 0x6827u, 0x18C0u, 0x08E1u, 0x3882u, 0x28A3u,
    0xCB7Du, 0xDB5Cu, 0xEB3Fu, 0xFB1Eu, 0x8BF9u, 0x9BD8u, 0xABBBu, 0xBB9Au,
    0x4A75u, 0x5A54u, 0x6A37u, 0x7A16u, 0x0AF1u, 0x1AD0u, 0x2AB3u, 0x3A92u,
    0xFD2Eu, 0xED0Fu, 0xDD6Cu, 0xCD4Du, 0xBDAAu, 0xAD8Bu, 0x9DE8u, 0x8DC9u,
    0x7C26u, 0x6C07u, 0x5C64u, 0x4C45u, 0x3CA2u, 0x2C83u, 0x1CE0u, 0x0CC1u,
    0xEF1Fu, 0xFF3Eu, 0xCF5Du, 0xDF7Cu, 0xAF9Bu, 0xBFBAu, 0x8FD9u, 0x9FF8u,
    0x6E17u, 0x7E36u, 0x4E55u, 0x5E74u, 0x2E93u, 0x3EB2u, 0x0ED1u, 0x1EF0u,
};

uint16_t hp_crc16(uint16_t crc, const uint8_t *data, size_t len)
{
    /* table-driven, MSB first: crc = (crc << 8) ^ T[(crc >> 8) ^ byte] */
    const uint8_t *end = data + len;
    while (data != end) {
        uint8_t x = (uint8_t)((uint8_t)(crc >> 8) ^ *data++);
        crc = (uint16_t)((uint16_t)(crc << 8) ^ HP_ROM_U16(&crc_table[x]));
    }
    return crc;
}

/* ------------------------------------------------------------------ COBS */

size_t hp_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t out_size)
{
    /* pointers and an 8-bit run counter: an 8-bit MCU indexes with 16-bit adds otherwise */
    const uint8_t *end = in + len;
    uint8_t *o = out + 1, *code_at = out;
    uint8_t code = 1;
    if (out_size < len + len / 254u + 1u) {
        return 0;
    }
    while (in != end) {
        uint8_t b = *in++;
        if (b == 0) {
            *code_at = code;
            code_at = o++;
            code = 1;
        } else {
            *o++ = b;
            if (++code == 0xFFu) {
                *code_at = code;
                code_at = o++;
                code = 1;
            }
        }
    }
    *code_at = code;
    return (size_t)(o - out);
}

size_t hp_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_size)
{
    const uint8_t *end = in + len;
    uint8_t *o = out, *o_end = out + out_size;
    while (in != end) {
        uint8_t code = *in++, k;
        if (code == 0 || (size_t)(code - 1u) > (size_t)(end - in) ||
            (size_t)(code - 1u) > (size_t)(o_end - o)) {
            return (size_t)-1;
        }
        for (k = (uint8_t)(code - 1u); k; k--) {
            uint8_t b = *in++;
            if (b == 0) {
                return (size_t)-1;
            }
            *o++ = b;
        }
        if (code != 0xFFu && in != end) {
            if (o == o_end) {
                return (size_t)-1;
            }
            *o++ = 0;
        }
    }
    return (size_t)(o - out);
}

/* ------------------------------------------------------------------ little-endian fields */

static uint8_t *put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    return p + 2;
}

static uint8_t *put_u32(uint8_t *p, uint32_t v)
{
    /* constant shifts: byte moves on an 8-bit MCU (a variable shift is a bit loop) */
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
    return p + 4;
}

static uint8_t *put_u64(uint8_t *p, uint64_t v)
{
    /* two 32-bit halves: 64-bit shifts by a variable count are library calls on AVR */
    put_u32(p, (uint32_t)v);
    return put_u32(p + 4, (uint32_t)(v >> 32));
}

static uint8_t *put_f64(uint8_t *p, hp_f64_t v)
{
#ifdef HP_F64_AS_BITS
    put_u32(p, v.lo);
    return put_u32(p + 4, v.hi);
#else
    uint64_t bits;
    memcpy(&bits, &v, sizeof bits);
    return put_u64(p, bits);
#endif
}

static uint16_t get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
           ((uint32_t)p[3] << 24);
}

static uint64_t get_u64(const uint8_t *p)
{
    return (uint64_t)get_u32(p) | ((uint64_t)get_u32(p + 4) << 32);
}

static hp_f64_t get_f64(const uint8_t *p)
{
#ifdef HP_F64_AS_BITS
    hp_b64_t v;
    v.lo = get_u32(p);
    v.hi = get_u32(p + 4);
    return v;
#else
    uint64_t bits = get_u64(p);
    double v;
    memcpy(&v, &bits, sizeof v);
    return v;
#endif
}

/* ------------------------------------------------------------------ encoder */

/* seq then n f64 (FORCE, VELOCITY); NULL when n is not 1..8. */
static uint8_t *put_seq_axes(uint8_t *p, uint32_t seq, uint8_t n, const hp_f64_t *v)
{
    uint8_t i;
    if (n < 1 || n > HP_MAX_AXES) {
        return 0;
    }
    p = put_u32(p, seq);
    for (i = 0; i < n; i++) {
        p = put_f64(p, v[i]);
    }
    return p;
}

/* seq then the f64 filling the rest of a packet of n bytes (type + body, FORCE and
 * VELOCITY); the axis count, 0 when the length is not 5 + 8 k with k in 1..8. */
static uint8_t get_seq_axes(const uint8_t *p, size_t n, uint32_t *seq, hp_f64_t *v)
{
    uint8_t i, k;
    if (n < HP_FORCE_FIXED + 8u || n > HP_FORCE_FIXED + 8u * HP_MAX_AXES ||
        (n - HP_FORCE_FIXED) % 8u != 0) {
        return 0;
    }
    *seq = get_u32(p);
    k = (uint8_t)((n - HP_FORCE_FIXED) / 8u);
    for (i = 0; i < k; i++) {
        v[i] = get_f64(p + 4 + 8 * i);
    }
    return k;
}

/* n binary32 bit patterns, little-endian. */
static uint8_t *put_f32s(uint8_t *p, uint8_t n, const uint32_t *v)
{
    uint8_t i;
    for (i = 0; i < n; i++) {
        p = put_u32(p, v[i]);
    }
    return p;
}

/* The binary32 values filling the rest of a packet of n bytes after `fixed` bytes; the
 * axis count, 0 when the length is not fixed + 4 k with k in 1..8. */
static uint8_t get_f32s(const uint8_t *p, size_t n, size_t fixed, uint32_t *v)
{
    uint8_t i, k;
    if (n < fixed + 4u || n > fixed + 4u * HP_MAX_AXES || (n - fixed) % 4u != 0) {
        return 0;
    }
    k = (uint8_t)((n - fixed) / 4u);
    for (i = 0; i < k; i++) {
        v[i] = get_u32(p + 4 * i);
    }
    return k;
}

uint32_t hp_compact_seq(uint32_t now, uint16_t low)
{
    return now - (uint16_t)((uint16_t)now - low);
}

/* Packet body without CRC; returns its length or 0 on an invalid message. */
static size_t pack(const hp_msg_t *m, uint8_t *p0)
{
    uint8_t *p = p0;
    unsigned i;
    *p++ = m->type;
    switch (m->type) {
    case HP_MSG_HELLO:
        if (m->u.hello.n_axes < 1 || m->u.hello.n_axes > HP_MAX_AXES) {
            return 0;
        }
        *p++ = m->u.hello.protocol_version;
        *p++ = m->u.hello.n_axes;
        p = put_u32(p, m->u.hello.device_id);
        p = put_f64(p, m->u.hello.position_scale);
        p = put_f64(p, m->u.hello.force_scale);
        p = put_f64(p, m->u.hello.force_limit);
        p = put_f64(p, m->u.hello.native_rate_hz);
        break;
    case HP_MSG_HELLO_REQUEST:
        *p++ = m->u.hello_request.protocol_version;
        break;
    case HP_MSG_CONFIG:
        p = put_f64(p, m->u.config.rate_hz);
        p = put_u32(p, m->u.config.watchdog_us);
        p = put_f64(p, m->u.config.force_limit);
        break;
    case HP_MSG_STATE:
        if (m->u.state.n_axes < 1 || m->u.state.n_axes > HP_MAX_AXES) {
            return 0;
        }
        p = put_u32(p, m->u.state.seq);
        p = put_u64(p, m->u.state.time_us);
        p = put_u16(p, m->u.state.status);
        p = put_u32(p, m->u.state.force_seq);
        for (i = 0; i < m->u.state.n_axes; i++) {
            p = put_f64(p, m->u.state.position[i]);
        }
        break;
    case HP_MSG_FORCE:
        p = put_seq_axes(p, m->u.force.seq, m->u.force.n_axes, m->u.force.force);
        break;
    case HP_MSG_LINK:
        p = put_u32(p, m->u.link.baud);
        *p++ = m->u.link.bits_per_byte;
        break;
    case HP_MSG_SENSORS_REQUEST:
        p = put_u16(p, m->u.sensors_request.sensors);
        break;
    case HP_MSG_SENSORS:
        p = put_u16(p, m->u.sensors.offered);
        p = put_u16(p, m->u.sensors.enabled);
        break;
    case HP_MSG_VELOCITY: /* FORCE's layout */
        p = put_seq_axes(p, m->u.velocity.seq, m->u.velocity.n_axes, m->u.velocity.velocity);
        break;
    case HP_MSG_STATE_COMPACT:
        if (m->u.state_compact.n_axes < 1 || m->u.state_compact.n_axes > HP_MAX_AXES) {
            return 0;
        }
        p = put_u16(p, m->u.state_compact.seq);
        *p++ = m->u.state_compact.status;
        *p++ = m->u.state_compact.lag;
        p = put_f32s(p, m->u.state_compact.n_axes, m->u.state_compact.position);
        break;
    case HP_MSG_FORCE_COMPACT:
        if (m->u.force_compact.n_axes < 1 || m->u.force_compact.n_axes > HP_MAX_AXES) {
            return 0;
        }
        p = put_u16(p, m->u.force_compact.seq);
        p = put_f32s(p, m->u.force_compact.n_axes, m->u.force_compact.force);
        break;
    case HP_MSG_PING:
        p = put_u32(p, m->u.ping.nonce);
        p = put_u64(p, m->u.ping.host_time_us);
        break;
    case HP_MSG_PONG:
        p = put_u32(p, m->u.pong.nonce);
        p = put_u64(p, m->u.pong.host_time_us);
        p = put_u64(p, m->u.pong.device_time_us);
        break;
    case HP_MSG_FAULT:
        p = put_u16(p, m->u.fault.code);
        p = put_u32(p, m->u.fault.detail);
        break;
    case HP_MSG_STOP:
        break;
    default:
        return 0;
    }
    return p ? (size_t)(p - p0) : 0; /* NULL: an axis count not 1..8 */
}

size_t hp_encode(const hp_msg_t *msg, uint8_t *out, size_t out_size)
{
    uint8_t packet[HP_MAX_PACKET];
    size_t n = pack(msg, packet);
    size_t o;
    uint16_t crc;
    if (n == 0) {
        return 0;
    }
    crc = hp_crc16(0xFFFFu, packet, n);
    packet[n++] = (uint8_t)(crc >> 8); /* CRC is sent MSB first */
    packet[n++] = (uint8_t)crc;
    if (out_size < 1) {
        return 0;
    }
    o = hp_cobs_encode(packet, n, out, out_size - 1);
    if (o == 0) {
        return 0;
    }
    out[o++] = 0;
    return o;
}

/* ------------------------------------------------------------------ decoder */

static int fixed_len(size_t len, size_t want)
{
    return len == want ? HP_OK : HP_ERR_MALFORMED;
}

int hp_decode_packet(const uint8_t *pk, size_t len, hp_msg_t *m)
{
    const uint8_t *p = pk + 1;
    size_t n, i;
    if (len < 3) {
        return HP_ERR_BAD_CRC;
    }
    if (len > HP_MAX_PACKET) {
        return HP_ERR_OVERLONG;
    }
    /* With the CRC appended MSB first, the CRC of the whole packet is zero. */
    if (hp_crc16(0xFFFFu, pk, len) != 0) {
        return HP_ERR_BAD_CRC;
    }
    n = len - 2; /* type + body */
    m->type = pk[0];
    switch (pk[0]) {
    case HP_MSG_HELLO:
        if (n != 39) {
            return HP_ERR_MALFORMED;
        }
        m->u.hello.protocol_version = p[0];
        m->u.hello.n_axes = p[1];
        if (p[1] < 1 || p[1] > HP_MAX_AXES) {
            return HP_ERR_MALFORMED;
        }
        m->u.hello.device_id = get_u32(p + 2);
        m->u.hello.position_scale = get_f64(p + 6);
        m->u.hello.force_scale = get_f64(p + 14);
        m->u.hello.force_limit = get_f64(p + 22);
        m->u.hello.native_rate_hz = get_f64(p + 30);
        return HP_OK;
    case HP_MSG_HELLO_REQUEST:
        m->u.hello_request.protocol_version = p[0];
        return fixed_len(n, 2);
    case HP_MSG_CONFIG:
        if (n != 21) {
            return HP_ERR_MALFORMED;
        }
        m->u.config.rate_hz = get_f64(p);
        m->u.config.watchdog_us = get_u32(p + 8);
        m->u.config.force_limit = get_f64(p + 12);
        return HP_OK;
    case HP_MSG_LINK:
        if (n != 6) {
            return HP_ERR_MALFORMED;
        }
        m->u.link.baud = get_u32(p);
        m->u.link.bits_per_byte = p[4];
        return HP_OK;
    case HP_MSG_SENSORS_REQUEST:
        if (n != 3) {
            return HP_ERR_MALFORMED;
        }
        m->u.sensors_request.sensors = get_u16(p);
        return HP_OK;
    case HP_MSG_SENSORS:
        if (n != 5) {
            return HP_ERR_MALFORMED;
        }
        m->u.sensors.offered = get_u16(p);
        m->u.sensors.enabled = get_u16(p + 2);
        return HP_OK;
    case HP_MSG_VELOCITY: /* FORCE's layout: seq, f64[n] */
        m->u.velocity.n_axes = get_seq_axes(p, n, &m->u.velocity.seq, m->u.velocity.velocity);
        return m->u.velocity.n_axes ? HP_OK : HP_ERR_MALFORMED;
    case HP_MSG_STATE:
        if (n < HP_STATE_FIXED + 8u || n > HP_STATE_FIXED + 8u * HP_MAX_AXES ||
            (n - HP_STATE_FIXED) % 8u != 0) {
            return HP_ERR_MALFORMED;
        }
        m->u.state.seq = get_u32(p);
        m->u.state.time_us = get_u64(p + 4);
        m->u.state.status = get_u16(p + 12);
        m->u.state.force_seq = get_u32(p + 14);
        m->u.state.n_axes = (uint8_t)((n - HP_STATE_FIXED) / 8u);
        for (i = 0; i < m->u.state.n_axes; i++) {
            m->u.state.position[i] = get_f64(p + 18 + 8 * i);
        }
        return HP_OK;
    case HP_MSG_FORCE:
        m->u.force.n_axes = get_seq_axes(p, n, &m->u.force.seq, m->u.force.force);
        return m->u.force.n_axes ? HP_OK : HP_ERR_MALFORMED;
    case HP_MSG_STATE_COMPACT:
        m->u.state_compact.n_axes = get_f32s(p + 4, n, HP_STATE_C_FIXED,
                                             m->u.state_compact.position);
        if (!m->u.state_compact.n_axes) {
            return HP_ERR_MALFORMED;
        }
        m->u.state_compact.seq = get_u16(p);
        m->u.state_compact.status = p[2];
        m->u.state_compact.lag = p[3];
        return HP_OK;
    case HP_MSG_FORCE_COMPACT:
        m->u.force_compact.n_axes = get_f32s(p + 2, n, HP_FORCE_C_FIXED,
                                             m->u.force_compact.force);
        if (!m->u.force_compact.n_axes) {
            return HP_ERR_MALFORMED;
        }
        m->u.force_compact.seq = get_u16(p);
        return HP_OK;
    case HP_MSG_PING:
        if (n != 13) {
            return HP_ERR_MALFORMED;
        }
        m->u.ping.nonce = get_u32(p);
        m->u.ping.host_time_us = get_u64(p + 4);
        return HP_OK;
    case HP_MSG_PONG:
        if (n != 21) {
            return HP_ERR_MALFORMED;
        }
        m->u.pong.nonce = get_u32(p);
        m->u.pong.host_time_us = get_u64(p + 4);
        m->u.pong.device_time_us = get_u64(p + 12);
        return HP_OK;
    case HP_MSG_FAULT:
        if (n != 7) {
            return HP_ERR_MALFORMED;
        }
        m->u.fault.code = get_u16(p);
        m->u.fault.detail = get_u32(p + 2);
        return HP_OK;
    case HP_MSG_STOP:
        return fixed_len(n, 1);
    default:
        return HP_ERR_UNKNOWN_TYPE;
    }
}

int hp_decode_frame(const uint8_t *frame, size_t len, hp_msg_t *msg)
{
    uint8_t buf[HP_MAX_FRAME];
    size_t n;
    if (len > 0 && frame[len - 1] == 0) {
        len--;
    }
    if (len > HP_MAX_FRAME - 1u) {
        return HP_ERR_OVERLONG;
    }
    if (len == 0) {
        return HP_ERR_BAD_COBS;
    }
    n = hp_cobs_decode(frame, len, buf, sizeof buf);
    if (n == (size_t)-1) {
        return HP_ERR_BAD_COBS;
    }
    return hp_decode_packet(buf, n, msg);
}

void hp_decoder_init(hp_decoder_t *dec)
{
    memset(dec, 0, sizeof *dec);
}

int hp_decoder_feed(hp_decoder_t *dec, uint8_t byte, hp_msg_t *msg)
{
    size_t n;
    int r;
    if (byte != 0) {
        if (dec->overflow) {
            return HP_NONE;
        }
        if (dec->len >= HP_MAX_FRAME - 1u) {
            dec->overflow = 1; /* drop the rest of this frame */
            return HP_NONE;
        }
        dec->buf[dec->len++] = byte;
        return HP_NONE;
    }
    /* Delimiter: a frame ends here. */
    if (dec->overflow) {
        dec->overflow = 0;
        dec->len = 0;
        dec->overlong++;
        return HP_ERR_OVERLONG;
    }
    if (dec->len == 0) {
        return HP_NONE; /* idle fill */
    }
    n = hp_cobs_decode(dec->buf, dec->len, dec->buf, sizeof dec->buf); /* in place */
    dec->len = 0;
    r = (n == (size_t)-1) ? HP_ERR_BAD_COBS : hp_decode_packet(dec->buf, n, msg);
    switch (r) {
    case HP_OK: dec->frames_ok++; break;
    case HP_ERR_BAD_COBS: dec->bad_cobs++; break;
    case HP_ERR_BAD_CRC: dec->bad_crc++; break;
    case HP_ERR_OVERLONG: dec->overlong++; break;
    case HP_ERR_UNKNOWN_TYPE: dec->unknown_type++; break;
    default: dec->malformed++; break;
    }
    return r;
}

/* ------------------------------------------------------------------ device-side duties */

#ifndef HP_F64_AS_BITS
uint16_t hp_limit_force(double *force, uint8_t n, double limit)
{
    uint16_t status = 0;
    uint8_t i;
    for (i = 0; i < n; i++) {
        double f = force[i];
        if (f != f || f - f != 0.0) { /* NaN, or inf (inf - inf is NaN) */
            for (i = 0; i < n; i++) {
                force[i] = 0.0;
            }
            return HP_STATUS_FAULT;
        }
    }
    for (i = 0; i < n; i++) {
        if (force[i] > limit) {
            force[i] = limit;
            status = HP_STATUS_FORCE_CLAMPED;
        } else if (force[i] < -limit) {
            force[i] = -limit;
            status = HP_STATUS_FORCE_CLAMPED;
        }
    }
    return status;
}

#endif

int hp_watchdog_expired(uint64_t last_force_us, uint64_t now_us, uint32_t timeout_us)
{
    return (uint64_t)(now_us - last_force_us) > (uint64_t)timeout_us;
}

/* ------------------------------------------------------------------ binary32 <-> binary64 */

/* The shifts below are split at byte boundaries (x << 20 as (x << 4) << 16, ...): an 8-bit
 * MCU moves whole bytes for free and shifts bit by bit, so this is a few dozen cycles
 * instead of hundreds. */
hp_b64_t hp_b64_from_f32_bits(uint32_t f)
{
    hp_b64_t r;
    uint32_t sign = f & 0x80000000u;
    uint16_t e = (uint16_t)((uint16_t)(f >> 16) >> 7) & 0xFFu;
    uint32_t m = f & 0x7FFFFFu;
    uint16_t e64;
    if (e == 0xFFu) {
        e64 = 0x7FFu; /* inf or NaN: the payload stays in the top mantissa bits */
    } else if (e == 0) {
        if (m == 0) {
            r.hi = sign; /* +-0 */
            r.lo = 0;
            return r;
        }
        /* subnormal m * 2^-149: normalise (every binary32 subnormal is binary64-normal) */
        e64 = 1u - 127u + 1023u;
        while ((m & 0x800000u) == 0) {
            m <<= 1;
            e64--;
        }
        m &= 0x7FFFFFu;
    } else {
        e64 = (uint16_t)(e - 127u + 1023u);
    }
    /* binary64 mantissa = m << 29: its top 20 bits in hi, the low 3 bits of m in lo */
    r.hi = sign | ((uint32_t)(uint16_t)(e64 << 4) << 16) | (m >> 3);
    r.lo = (uint32_t)(uint8_t)((uint8_t)m << 5) << 24;
    return r;
}

uint32_t hp_f32_bits_from_b64(hp_b64_t d)
{
    uint32_t sign = d.hi & 0x80000000u;
    int16_t e = (int16_t)(((uint16_t)(d.hi >> 16) >> 4) & 0x7FFu);
    uint32_t mhi = d.hi & 0xFFFFFu; /* mantissa bits 32..51 */
    int16_t E;
    if (e == 0x7FF) {
        if (mhi == 0 && d.lo == 0) {
            return sign | 0x7F800000u; /* +-inf */
        }
        return sign | 0x7FC00000u | (mhi << 3) | (d.lo >> 29); /* quiet NaN */
    }
    if (e == 0) {
        return sign; /* binary64 subnormal: far below half the least binary32 subnormal */
    }
    E = (int16_t)(e - 1023);
    if (E > 127) {
        return sign | 0x7F800000u; /* overflow: +-inf */
    }
    if (E >= -126) {
        /* normal: exponent field and top 23 mantissa bits in one word, so a rounding carry
         * moves into the exponent (and from the largest finite value to inf) by itself */
        uint8_t top = (uint8_t)(d.lo >> 24);
        uint32_t q = ((uint32_t)(uint16_t)((uint16_t)(E + 127) << 7) << 16) | (mhi << 3) |
                     (uint8_t)(top >> 5);
        /* the 29 bits dropped, against half of the last bit kept (2^28) */
        uint8_t r5 = top & 0x1Fu;
        uint8_t above = r5 > 0x10u || (r5 == 0x10u && (d.lo & 0xFFFFFFu) != 0);
        uint8_t tie = r5 == 0x10u && (d.lo & 0xFFFFFFu) == 0;
        if (above || (tie && (q & 1u))) {
            q++;
        }
        return sign | q;
    }
    /* subnormal (or zero) in binary32: units of 2^-149, value = (2^52 + m) * 2^(E - 52),
     * so the result is (2^52 + m) >> (-E - 97), rounded to nearest, ties to even */
    {
        uint32_t sh = (uint32_t)(-(int32_t)E - 97); /* 30 for E = -127 */
        uint64_t sig = ((uint64_t)(mhi | 0x100000u) << 32) | d.lo;
        uint64_t q, rem, half;
        if (sh > 54u) {
            return sign; /* below a quarter of the least subnormal: +-0 */
        }
        q = sig >> sh;
        rem = sig & (((uint64_t)1 << sh) - 1u);
        half = (uint64_t)1 << (sh - 1u);
        if (rem > half || (rem == half && (q & 1u))) {
            q++;
        }
        return sign | (uint32_t)q;
    }
}
