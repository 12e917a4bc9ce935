/*
 * vectors_test.c -- a test build of the firmware's codec for the emulated chip: it proves
 * on the AVR itself (32-bit double, the real hproto.c and uart.c) that the golden vectors
 * decode and encode as the Python codec says, and that binary64 <-> binary32 conversion
 * is exact.
 *
 * Every frame the UART interrupt cuts out (as in the firmware) is fed byte by byte to the
 * stream decoder hp_decoder_feed. For each frame, the answer is one frame of the test-only
 * type 0x7E:
 *     0x7E | result:i8 | hp_encode(decoded message), when result is HP_OK | crc
 * For a frame of the test-only type 0x7D (a request: 0x7D | k binary64 patterns | crc,
 * k <= 10), which the decoder counts as an unknown type, the answer is one frame 0x7D with,
 * for each pattern d, hp_f32_bits_from_b64(d) (u32) and the binary64 of that float32,
 * hp_b64_from_f32_bits (u64), little-endian.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <string.h>

#include "../../c/hproto.h"
#include "uart.h"

#define TEST_ECHO 0x7Eu
#define TEST_CONVERT 0x7Du

static void send_packet(uint8_t *pk, size_t n)
{
    uint8_t frame[HP_MAX_FRAME];
    uint16_t crc = hp_crc16(0xFFFFu, pk, n);
    size_t o;
    pk[n++] = (uint8_t)(crc >> 8);
    pk[n++] = (uint8_t)crc;
    o = hp_cobs_encode(pk, n, frame, sizeof frame - 1u);
    frame[o++] = 0;
    while (!uart_put(frame, o)) {
    }
}

static void convert(const uint8_t *pk, size_t n)
{
    static uint8_t out[HP_MAX_PACKET];
    size_t k = (n - 3u) / 8u, i, j, o = 1;
    out[0] = TEST_CONVERT;
    for (i = 0; i < k && i < 10u; i++) {
        hp_b64_t d = {0, 0}, w;
        uint32_t f;
        for (j = 0; j < 4u; j++) {
            d.lo |= (uint32_t)pk[1u + 8u * i + j] << (8u * j);
            d.hi |= (uint32_t)pk[5u + 8u * i + j] << (8u * j);
        }
        f = hp_f32_bits_from_b64(d);
        w = hp_b64_from_f32_bits(f);
        for (j = 0; j < 4u; j++) {
            out[o++] = (uint8_t)(f >> (8u * j));
        }
        for (j = 0; j < 4u; j++) {
            out[o++] = (uint8_t)(w.lo >> (8u * j));
        }
        for (j = 0; j < 4u; j++) {
            out[o++] = (uint8_t)(w.hi >> (8u * j));
        }
    }
    send_packet(out, o);
}

int main(void)
{
    static hp_decoder_t dec;
    static uint8_t raw[HP_MAX_FRAME];
    static uint8_t out[HP_MAX_PACKET];
    static const uint8_t ff = 0xFF;
    hp_msg_t m;
    hp_decoder_init(&dec);
    uart_init();
    sei();
    for (;;) {
        const uint8_t *frame;
        uint8_t len = uart_frame(&frame), i;
        int r = HP_NONE;
        if (!len) {
            continue;
        }
        /* the stream decoder, byte by byte as from the line (an over-long frame: 128 bytes) */
        for (i = 0; len == UART_OVERLONG ? i < 128u : i < len; i++) {
            (void)hp_decoder_feed(&dec, len == UART_OVERLONG ? ff : frame[i], &m);
        }
        if (len != UART_OVERLONG) {
            memcpy(raw, frame, len);
        }
        uart_frame_done();
        r = hp_decoder_feed(&dec, 0, &m);
        if (r == HP_ERR_UNKNOWN_TYPE && len > 1 && raw[1] == TEST_CONVERT) {
            size_t n = hp_cobs_decode(raw, len, raw, sizeof raw);
            if (n != (size_t)-1 && n >= 3u) {
                convert(raw, n);
            }
            continue;
        }
        out[0] = TEST_ECHO;
        out[1] = (uint8_t)(int8_t)r;
        {
            size_t n = 2;
            if (r == HP_OK) {
                n += hp_encode(&m, out + 2, sizeof out - 4u);
            }
            send_packet(out, n);
        }
    }
}
