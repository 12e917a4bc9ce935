/*
 * hk_shared.h -- what the Hapkit 3 firmware (main.c) and the Hapkit pantograph firmware
 * (../pantograph/pantograph.c) share on the chip: the binary64 helpers of the wire (avr-gcc's
 * double is 32-bit: values are carried as hp_b64_t bit patterns) and the motor's PWM on
 * D5/D8 (hapkit_geometry.h). Static: each firmware keeps its own copy, compiled
 * where it is used (the same code as when they were written in main.c).
 */
#ifndef HK_SHARED_H
#define HK_SHARED_H

#include <avr/io.h>
#include <stdint.h>
#include <string.h>

#include "../../c/hproto.h"

/* float32 x as the exact binary64 the wire carries. */
static __attribute__((unused)) hp_b64_t f64_of_float(float x)
{
    uint32_t b;
    memcpy(&b, &x, sizeof b);
    return hp_b64_from_f32_bits(b);
}

/* binary64 d rounded to float32 (round to nearest, ties to even; in integer code). */
static __attribute__((unused)) float float_of_f64(hp_b64_t d)
{
    uint32_t b = hp_f32_bits_from_b64(d);
    float x;
    memcpy(&x, &b, sizeof x);
    return x;
}

static __attribute__((unused)) uint8_t f64_is_finite(hp_b64_t d)
{
    return ((d.hi >> 20) & 0x7FFu) != 0x7FFu;
}

/* The value of binary64 `b` when it is a whole number in 0..2^32-1: 1, else 0. */
static __attribute__((unused)) uint8_t f64_to_u32_exact(hp_b64_t b, uint32_t *out)
{
    uint64_t d = ((uint64_t)b.hi << 32) | b.lo;
    int16_t e = (int16_t)((d >> 52) & 0x7FFu);
    uint64_t m = d & 0xFFFFFFFFFFFFFULL;
    int16_t sh;
    if (d == 0) {
        *out = 0;
        return 1;
    }
    if ((d >> 63) || e < 1023 || e > 1023 + 31) {
        return 0;
    }
    m |= 1ULL << 52;
    sh = (int16_t)(52 - (e - 1023));
    if (m & ((1ULL << sh) - 1u)) {
        return 0; /* a fraction */
    }
    *out = (uint32_t)(m >> sh);
    return 1;
}

/* The motor: duty n / 256 on D5 (Timer0 OC0B, fast PWM; n = 0: OC0B off, the pin is
 * PORTD5 = 0) and the direction on D8 (PB0, high = positive). */
static __attribute__((unused)) void pwm_write(uint16_t n, uint8_t dir)
{
    if (dir) {
        PORTB |= (uint8_t)(1 << PB0);
    } else {
        PORTB &= (uint8_t)~(1 << PB0);
    }
    if (n == 0) {
        TCCR0A &= (uint8_t)~(1 << COM0B1);
    } else {
        OCR0B = (uint8_t)(n - 1u);
        TCCR0A |= (uint8_t)(1 << COM0B1);
    }
}

#endif /* HK_SHARED_H */
