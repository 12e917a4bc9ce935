/*
 * hproto.h -- reference C99 implementation of the hapsim framed serial protocol.
 *
 * Specification: ../PROTOCOL.md. Golden vectors: ../vectors/vectors.json.
 *
 * Portable C99 for firmware: no malloc, no stdio, only <stdint.h> and <string.h> (which
 * also defines size_t, C99 7.21.1).
 * Frame on the wire: COBS(type:u8 | body | crc16:u16 MSB first) followed by one 0x00.
 * Bodies are little-endian with no padding; positions and forces are IEEE-754 binary64.
 *
 * Where the compiler's `double` is 64-bit, f64 fields are `double` (hp_f64_t). Where it is
 * narrower (AVR-GCC: 32-bit double), or when HP_F64_AS_BITS is defined, f64 fields are
 * carried as their binary64 bit patterns (hp_f64_t = hp_b64_t), and the firmware converts
 * them exactly with hp_b64_from_f32_bits / hp_f32_bits_from_b64 (integer code, IEEE-754
 * round to nearest, ties to even). hp_limit_force needs a 64-bit double.
 */
#ifndef HPROTO_H
#define HPROTO_H

#include <stdint.h>
#include <string.h>

#ifdef __cplusplus
extern "C" {
#endif

#define HP_PROTOCOL_VERSION 1u
#define HP_MAX_FRAME 128u  /* bytes on the wire, delimiter included */
#define HP_MAX_PACKET 126u /* type + body + CRC, before COBS */
#define HP_MAX_AXES 8u

#if !defined(HP_F64_AS_BITS) && defined(__SIZEOF_DOUBLE__) && __SIZEOF_DOUBLE__ != 8
#define HP_F64_AS_BITS 1
#endif
/* An IEEE-754 binary64 bit pattern as two 32-bit halves (an 8-bit MCU handles 32-bit words
 * inline but calls a library routine for every 64-bit shift). */
typedef struct {
    uint32_t lo; /* mantissa bits 0..31 */
    uint32_t hi; /* sign, exponent, mantissa bits 32..51 */
} hp_b64_t;
#ifdef HP_F64_AS_BITS
typedef hp_b64_t hp_f64_t;
#else
typedef double hp_f64_t;
#endif

/* Message type ids. */
#define HP_MSG_HELLO 0x01u
#define HP_MSG_HELLO_REQUEST 0x02u
#define HP_MSG_CONFIG 0x03u
#define HP_MSG_LINK 0x04u /* added within version 1 (PROTOCOL.md section 9) */
#define HP_MSG_SENSORS_REQUEST 0x05u /* added within version 1 */
#define HP_MSG_SENSORS 0x06u         /* added within version 1 */
#define HP_MSG_STATE 0x10u
#define HP_MSG_FORCE 0x11u
#define HP_MSG_VELOCITY 0x12u        /* added within version 1 */
/* STATE_COMPACT / FORCE_COMPACT: STATE and FORCE with 16-bit seq and binary32 values, only
 * while the host enabled HP_FEATURE_COMPACT (PROTOCOL.md section 4, "Compact frames").
 * Added within version 1. */
#define HP_MSG_STATE_COMPACT 0x13u
#define HP_MSG_FORCE_COMPACT 0x14u
#define HP_MSG_PING 0x20u
#define HP_MSG_PONG 0x21u
#define HP_MSG_FAULT 0x30u
#define HP_MSG_STOP 0x31u

/* STATE.status bits. */
#define HP_STATUS_ARMED 0x0001u
#define HP_STATUS_WATCHDOG_TRIPPED 0x0002u
#define HP_STATUS_FORCE_CLAMPED 0x0004u
#define HP_STATUS_FAULT 0x0008u
#define HP_STATUS_RX_ERROR 0x0010u
#define HP_STATUS_OVERRUN 0x0020u
#define HP_STATUS_CONFIGURED 0x0040u
/* force_seq names a FORCE applied since the last CONFIG (clear: none yet, force_seq
 * means nothing). Added within version 1 (PROTOCOL.md section 9). */
#define HP_STATUS_FORCE_APPLIED 0x0080u

/* Sensor bits of SENSORS_REQUEST.sensors, SENSORS.offered and SENSORS.enabled. */
#define HP_SENSOR_VELOCITY 0x0001u
/* ... and the compact frames (STATE_COMPACT instead of STATE, FORCE_COMPACT accepted). */
#define HP_FEATURE_COMPACT 0x0002u
#define HP_COMPACT_LAG_MAX 255u /* STATE_COMPACT.lag saturates here */

/* FAULT.code values. */
#define HP_FAULT_WATCHDOG 0x0001u
#define HP_FAULT_BAD_CONFIG 0x0002u
#define HP_FAULT_SENSOR 0x0003u
#define HP_FAULT_AMPLIFIER 0x0004u
#define HP_FAULT_NON_FINITE_FORCE 0x0005u
#define HP_FAULT_AXES_MISMATCH 0x0006u
#define HP_FAULT_RX_ERRORS 0x0007u
#define HP_FAULT_OVERRUN 0x0008u
#define HP_FAULT_VERSION_MISMATCH 0x0009u

/* Results of hp_decode_frame / hp_decoder_feed (negative: frame dropped). */
#define HP_OK 0
#define HP_NONE 1 /* hp_decoder_feed: no message completed by this byte */
#define HP_ERR_BAD_COBS (-1)
#define HP_ERR_BAD_CRC (-2)
#define HP_ERR_OVERLONG (-3)
#define HP_ERR_UNKNOWN_TYPE (-4)
#define HP_ERR_MALFORMED (-5)

typedef struct {
    uint8_t protocol_version;
    uint8_t n_axes;          /* 1..8 */
    uint32_t device_id;
    hp_f64_t position_scale;   /* [m/count] */
    hp_f64_t force_scale;      /* [N/unit] */
    hp_f64_t force_limit;      /* [N] */
    hp_f64_t native_rate_hz;   /* [Hz] */
} hp_hello_t;

typedef struct {
    uint8_t protocol_version;
} hp_hello_request_t;

typedef struct {
    hp_f64_t rate_hz;          /* [Hz] */
    uint32_t watchdog_us;    /* [us] */
    hp_f64_t force_limit;      /* [N] */
} hp_config_t;

typedef struct {
    uint32_t seq;
    uint64_t time_us;        /* [us] */
    uint16_t status;         /* HP_STATUS_* bits */
    uint32_t force_seq;
    uint8_t n_axes;          /* 1..8, not on the wire: implied by the length */
    hp_f64_t position[HP_MAX_AXES]; /* [m] */
} hp_state_t;

typedef struct {
    uint32_t seq;
    uint8_t n_axes;          /* 1..8, not on the wire: implied by the length */
    hp_f64_t force[HP_MAX_AXES]; /* [N] */
} hp_force_t;

typedef struct {
    uint32_t nonce;
    uint64_t host_time_us;   /* [us] */
} hp_ping_t;

/* LINK: the device's serial line, sent with HELLO so the host can check that STATE and
 * FORCE frames fit one tick at the rate it asks (PROTOCOL.md section 4). */
typedef struct {
    uint32_t baud;           /* [bit/s] */
    uint8_t bits_per_byte;   /* start + data + parity + stop bits, e.g. 10 for 8N1 */
} hp_link_t;

typedef struct {
    uint32_t nonce;
    uint64_t host_time_us;   /* [us] */
    uint64_t device_time_us; /* [us] */
} hp_pong_t;

/* SENSORS_REQUEST: the extra sensor messages the host asks for (HP_SENSOR_* bits; 0: none).
 * The device answers SENSORS at once (PROTOCOL.md section 4). */
typedef struct {
    uint16_t sensors;
} hp_sensors_request_t;

/* SENSORS: what the device can send and what it sends from now on (requested & offered). */
typedef struct {
    uint16_t offered;
    uint16_t enabled;
} hp_sensors_t;

/* VELOCITY: the measured velocity at the STATE with the same seq, sent just before it. */
typedef struct {
    uint32_t seq;
    uint8_t n_axes;          /* 1..8, not on the wire: implied by the length */
    hp_f64_t velocity[HP_MAX_AXES]; /* [m/s] */
} hp_velocity_t;

/* STATE_COMPACT: seq and status cut to their low bits, force_seq as the lag, positions as
 * IEEE-754 binary32 bit patterns (exact on every compiler; memcpy to a float to use). */
typedef struct {
    uint16_t seq;            /* low 16 bits of the tick counter */
    uint8_t status;          /* low 8 bits of the status */
    uint8_t lag;             /* seq - force_seq, saturated at 255; 0 without FORCE_APPLIED */
    uint8_t n_axes;          /* 1..8, not on the wire: implied by the length */
    uint32_t position[HP_MAX_AXES]; /* binary32 bits [m] */
} hp_state_compact_t;

/* FORCE_COMPACT: the low 16 bits of the answered STATE's seq, forces as binary32 bits. */
typedef struct {
    uint16_t seq;
    uint8_t n_axes;          /* 1..8, not on the wire: implied by the length */
    uint32_t force[HP_MAX_AXES]; /* binary32 bits [N] */
} hp_force_compact_t;

typedef struct {
    uint16_t code;           /* HP_FAULT_* */
    uint32_t detail;
} hp_fault_t;

/* A message: `type` selects the member of `u` (STOP has no body). */
typedef struct {
    uint8_t type;
    union {
        hp_hello_t hello;
        hp_hello_request_t hello_request;
        hp_config_t config;
        hp_link_t link;
        hp_state_t state;
        hp_force_t force;
        hp_ping_t ping;
        hp_pong_t pong;
        hp_fault_t fault;
        hp_sensors_request_t sensors_request;
        hp_sensors_t sensors;
        hp_velocity_t velocity;
        hp_state_compact_t state_compact;
        hp_force_compact_t force_compact;
    } u;
} hp_msg_t;

/* Stream decoder: a fixed buffer and counters; zero-initialise or call hp_decoder_init. */
typedef struct {
    uint8_t buf[HP_MAX_FRAME];
    size_t len;
    uint8_t overflow;        /* current frame is over-long: drop until the next 0x00 */
    uint32_t frames_ok;
    uint32_t bad_cobs;
    uint32_t bad_crc;
    uint32_t overlong;
    uint32_t unknown_type;
    uint32_t malformed;
} hp_decoder_t;

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xorout).
 * Pass crc = 0xFFFF to start. hp_crc16(0xFFFF, "123456789", 9) == 0x29B1. */
uint16_t hp_crc16(uint16_t crc, const uint8_t *data, size_t len);

/* COBS-encode `len` bytes into `out` (no delimiter). Returns the length written, or 0 if
 * `out_size` is too small. Needs out_size >= len + len / 254 + 1. */
size_t hp_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t out_size);

/* COBS-decode `len` bytes (no delimiter, no 0x00 inside) into `out`; `out` may equal `in`
 * (in-place). Returns the decoded length, or (size_t)-1 on a COBS error. */
size_t hp_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t out_size);

/* Encode `msg` as a whole frame (delimiter included) into `out`. Returns the frame length,
 * or 0 if the type is unknown, n_axes is not 1..8 or `out_size` is too small.
 * HP_MAX_FRAME bytes are always enough. */
size_t hp_encode(const hp_msg_t *msg, uint8_t *out, size_t out_size);

/* Decode a packet (type | body | crc, already COBS-decoded). Returns HP_OK or HP_ERR_*. */
int hp_decode_packet(const uint8_t *packet, size_t len, hp_msg_t *msg);

/* Decode one frame (with or without its trailing 0x00). `frame` is not modified.
 * Returns HP_OK or HP_ERR_*; `msg` is only meaningful on HP_OK. */
int hp_decode_frame(const uint8_t *frame, size_t len, hp_msg_t *msg);

void hp_decoder_init(hp_decoder_t *dec);

/* Feed one received byte. Returns HP_OK when it completes a good frame (then `*msg` holds
 * the message), HP_NONE when no frame ended or only an empty one, or HP_ERR_* when a frame
 * ended and was dropped (already counted). Never act on a message unless HP_OK. */
int hp_decoder_feed(hp_decoder_t *dec, uint8_t byte, hp_msg_t *msg);

/* ------------------------------------------------------------------ device-side duties
 * Helpers for PROTOCOL.md section 5 (the firmware still owns its timer and its actuator). */

/* Force rules applied to force[0..n) before it reaches the actuator. If any component is
 * not finite (NaN, +-inf), every component is set to 0 and HP_STATUS_FAULT is returned
 * (raise the latched fault HP_FAULT_NON_FINITE_FORCE). Otherwise each component is clamped
 * to [-limit, +limit] [N] and HP_STATUS_FORCE_CLAMPED is returned if any was; 0 if none.
 * `limit` is min(CONFIG.force_limit, HELLO.force_limit) >= 0. Needs IEEE semantics
 * (do not build with -ffast-math). */
#ifndef HP_F64_AS_BITS
uint16_t hp_limit_force(double *force, uint8_t n, double limit);
#endif

/* Exact widening of an IEEE-754 binary32 bit pattern to binary64 (every float32 value,
 * subnormals, infinities and NaN payloads included, is representable). */
hp_b64_t hp_b64_from_f32_bits(uint32_t f);

/* Narrowing of an IEEE-754 binary64 bit pattern to binary32, rounded to nearest with ties
 * to even as IEEE-754 requires (overflow gives +-inf, underflow subnormals or +-0; a NaN
 * stays a quiet NaN with its sign and the top of its payload). */
uint32_t hp_f32_bits_from_b64(hp_b64_t d);

/* The 32-bit seq of a FORCE_COMPACT (its low 16 bits `low`) on a device whose last STATE
 * had seq `now`: the number at or before `now` with those low bits (a FORCE answers a STATE
 * already sent), i.e. now - ((now - low) mod 2^16) (PROTOCOL.md section 4). */
uint32_t hp_compact_seq(uint32_t now, uint16_t low);

/* 1 when the watchdog has expired: more than `timeout_us` [us] elapsed between the last
 * valid FORCE (`last_force_us`) and `now_us`, on a free-running microsecond clock
 * (wrap-safe: the difference is taken modulo 2^64). 0 otherwise. */
int hp_watchdog_expired(uint64_t last_force_us, uint64_t now_us, uint32_t timeout_us);

#ifdef __cplusplus
}
#endif

#endif /* HPROTO_H */
