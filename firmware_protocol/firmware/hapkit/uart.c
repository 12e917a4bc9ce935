/* uart.c -- see uart.h. */
#include "uart.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#define TX_SIZE 256u /* a STATE (31), a FAULT (11), a PONG (25), LINK + HELLO (10 + 43) */

/* Both rings are 256-byte aligned, so that the interrupts below address a slot with the
 * ring's high address byte and the 8-bit index (no 16-bit add). */
static volatile uint8_t rx_ring[256] __attribute__((aligned(256))); /* as received, 0x00s too */
static volatile uint8_t rx_head, rx_tail; /* uint8_t: wraps at 256 */
static volatile uint8_t rx_frames;        /* delimiters in the ring not yet taken */
static volatile uint16_t rx_lost;
static uint8_t rx_frame[UART_FRAME_MAX];  /* the frame handed to the main loop */
static volatile uint8_t tx_buf[TX_SIZE] __attribute__((aligned(256)));
static volatile uint8_t tx_head, tx_tail; /* tail: read by the ISR; uint8_t wraps at 256 */

void uart_init(void)
{
    uint16_t ubrr = (uint16_t)(F_CPU / (8UL * HK_BAUD) - 1UL);
    /* frame format and U2X first: the line rate is taken when UBRR0L is written (so on
     * the chip, and so in simavr, which computes it at that write) */
    UCSR0A = (uint8_t)(1 << U2X0);
    UCSR0C = (uint8_t)((1 << UCSZ01) | (1 << UCSZ00)); /* 8N1 */
    UBRR0H = (uint8_t)(ubrr >> 8);
    UBRR0L = (uint8_t)ubrr;
    UCSR0B = (uint8_t)((1 << RXEN0) | (1 << TXEN0) | (1 << RXCIE0));
}

/* The two byte interrupts, written in assembly: at 2 Mbaud one comes every 80 cycles per
 * direction, and avr-gcc's prologue of the C version (r0, r1, SREG, r24, r25, r30, r31:
 * 56-59 cycles a byte) cost about a sixth of a 4 kHz tick. Same logic as the C it replaces:
 *
 *   RX:  b = UDR0; next = rx_head + 1;
 *        if (next == rx_tail) rx_lost++;       (ring full: the byte is lost, its frame
 *                                               fails its CRC)
 *        else { rx_ring[rx_head] = b; rx_head = next; if (b == 0) rx_frames++; }
 *                                              (the main loop is woken per frame)
 *   UDRE: t = tx_tail; if (t == tx_head) UCSR0B &= ~UDRIE0;
 *        else { UDR0 = tx_buf[t]; tx_tail = t + 1; }
 */
ISR(USART_RX_vect, ISR_NAKED)
{
    __asm__ __volatile__(
        "push r24\n\t"
        "in r24, __SREG__\n\t"
        "push r24\n\t"
        "push r25\n\t"
        "push r30\n\t"
        "push r31\n\t"
        "lds r25, %[udr]\n\t"
        "lds r30, %[head]\n\t"
        "mov r24, r30\n\t"
        "subi r24, 0xFF\n\t"          /* next = head + 1 */
        "lds r31, %[tail]\n\t"
        "cp r24, r31\n\t"
        "breq 2f\n\t"
        "ldi r31, hi8(%[ring])\n\t"
        "st Z, r25\n\t"
        "sts %[head], r24\n\t"
        "tst r25\n\t"
        "brne 1f\n\t"
        "lds r24, %[frames]\n\t"
        "subi r24, 0xFF\n\t"
        "sts %[frames], r24\n\t"
        "1: pop r31\n\t"
        "pop r30\n\t"
        "pop r25\n\t"
        "pop r24\n\t"
        "out __SREG__, r24\n\t"
        "pop r24\n\t"
        "reti\n\t"
        "2: lds r24, %[lost]\n\t"
        "lds r25, %[lost]+1\n\t"
        "adiw r24, 1\n\t"
        "sts %[lost]+1, r25\n\t"
        "sts %[lost], r24\n\t"
        "rjmp 1b\n\t"
        :
        : [udr] "n"(_SFR_MEM_ADDR(UDR0)), [head] "i"(&rx_head), [tail] "i"(&rx_tail),
          [ring] "i"(rx_ring), [frames] "i"(&rx_frames), [lost] "i"(&rx_lost));
}

ISR(USART_UDRE_vect, ISR_NAKED)
{
    __asm__ __volatile__(
        "push r24\n\t"
        "in r24, __SREG__\n\t"
        "push r24\n\t"
        "push r30\n\t"
        "push r31\n\t"
        "lds r30, %[tail]\n\t"
        "lds r24, %[head]\n\t"
        "cp r30, r24\n\t"
        "breq 2f\n\t"
        "ldi r31, hi8(%[buf])\n\t"
        "ld r24, Z\n\t"
        "sts %[udr], r24\n\t"
        "subi r30, 0xFF\n\t"
        "sts %[tail], r30\n\t"
        "1: pop r31\n\t"
        "pop r30\n\t"
        "pop r24\n\t"
        "out __SREG__, r24\n\t"
        "pop r24\n\t"
        "reti\n\t"
        "2: lds r24, %[ucsrb]\n\t"
        "andi r24, %[noudrie]\n\t"
        "sts %[ucsrb], r24\n\t"
        "rjmp 1b\n\t"
        :
        : [udr] "n"(_SFR_MEM_ADDR(UDR0)), [head] "i"(&tx_head), [tail] "i"(&tx_tail),
          [buf] "i"(tx_buf), [ucsrb] "n"(_SFR_MEM_ADDR(UCSR0B)),
          [noudrie] "n"((uint8_t) ~(1 << UDRIE0)));
}

uint8_t uart_frame_ready(void)
{
    return rx_frames;
}

uint8_t uart_frame(const uint8_t **frame)
{
    while (rx_frames) {
        uint8_t t = rx_tail, len = 0, over = 0, b;
        while ((b = rx_ring[t]) != 0) {
            if (len < UART_FRAME_MAX) {
                rx_frame[len++] = b;
            } else {
                over = 1;
            }
            t = (uint8_t)(t + 1u);
        }
        rx_tail = (uint8_t)(t + 1u); /* past the delimiter */
        {
            uint8_t s = SREG;
            cli();
            rx_frames--;
            SREG = s;
        }
        if (over) {
            *frame = rx_frame;
            return UART_OVERLONG;
        }
        if (len) {
            *frame = rx_frame;
            return len;
        }
        /* an empty frame: idle fill, skipped */
    }
    return 0;
}

void uart_frame_done(void)
{
}

uint8_t uart_put(const uint8_t *p, size_t len)
{
    uint8_t head = tx_head;
    uint8_t used = (uint8_t)(head - tx_tail);
    size_t i;
    if (len > (size_t)(TX_SIZE - 1u - used)) {
        return 0;
    }
    for (i = 0; i < len; i++) {
        tx_buf[head] = p[i];
        head = (uint8_t)(head + 1u);
    }
    tx_head = head;
    UCSR0B |= (uint8_t)(1 << UDRIE0);
    return 1;
}

uint16_t uart_rx_lost(void)
{
    uint16_t n;
    uint8_t s = SREG;
    cli();
    n = rx_lost;
    SREG = s;
    return n;
}

uint8_t uart_put_packet(const uint8_t *pk, uint8_t len)
{
    uint8_t head = tx_head, code_at, code = 1;
    if ((uint16_t)len + 2u > (uint16_t)(TX_SIZE - 1u - (uint8_t)(head - tx_tail))) {
        return 0;
    }
    code_at = head++;
    do {
        uint8_t b = *pk++;
        if (b) {
            tx_buf[head++] = b;
            code++; /* len <= 253: a group never reaches 0xFF */
        } else {
            tx_buf[code_at] = code;
            code_at = head++;
            code = 1;
        }
    } while (--len);
    tx_buf[code_at] = code;
    tx_buf[head++] = 0;
    tx_head = head;
    UCSR0B |= (uint8_t)(1 << UDRIE0);
    return 1;
}

uint8_t uart_packet(uint8_t *pk)
{
    while (rx_frames) {
        uint8_t t = rx_tail, raw = 0, left = 0, zero = 0, b, r = 0;
        uint8_t *o = pk;
        while ((b = rx_ring[t++]) != 0) {
            if (++raw > UART_FRAME_MAX) {
                while (rx_ring[t++] != 0) {
                } /* over-long: skipped up to its delimiter */
                r = UART_OVERLONG;
                break;
            }
            if (left) {
                *o++ = b;
                left--;
            } else { /* a code byte: the group before it ended with a zero */
                if (zero) {
                    *o++ = 0;
                }
                zero = b != 0xFFu;
                left = (uint8_t)(b - 1u);
            }
        }
        rx_tail = t; /* past the delimiter */
        {
            uint8_t s = SREG;
            cli();
            rx_frames--;
            SREG = s;
        }
        if (r) {
            return r;
        }
        if (left != 0) {
            return UART_BAD_COBS;
        }
        if (raw) {
            return (uint8_t)(o - pk);
        }
        /* an empty frame: idle fill, skipped */
    }
    return 0;
}
