/* uart.c -- see uart.h. */
#include "uart.h"

#include <avr/interrupt.h>
#include <avr/io.h>

#define TX_SIZE 256u /* a STATE (31), a FAULT (11), a PONG (25), LINK + HELLO (10 + 43) */

static volatile uint8_t rx_buf[2][UART_FRAME_MAX];
static uint8_t rx_w;                /* buffer the ISR fills */
static uint8_t rx_len;              /* its length so far; > UART_FRAME_MAX: over-long */
static volatile uint8_t rx_ready;   /* 1 + index of the frame waiting for the main loop */
static volatile uint8_t rx_ready_len;
static volatile uint16_t rx_lost;
static volatile uint8_t tx_buf[TX_SIZE];
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

ISR(USART_RX_vect)
{
    uint8_t b = UDR0;
    if (b != 0) {
        if (rx_len < UART_FRAME_MAX) {
            rx_buf[rx_w][rx_len] = b;
        }
        if (rx_len <= UART_FRAME_MAX) {
            rx_len++; /* stops at UART_FRAME_MAX + 1: over-long */
        }
        return;
    }
    if (rx_len == 0) {
        return; /* idle fill */
    }
    if (rx_ready) {
        rx_lost++; /* the main loop still holds the last frame */
    } else {
        rx_ready_len = rx_len > UART_FRAME_MAX ? UART_OVERLONG : rx_len;
        rx_ready = (uint8_t)(1u + rx_w);
        rx_w ^= 1u;
    }
    rx_len = 0;
}

ISR(USART_UDRE_vect)
{
    uint8_t t = tx_tail;
    if (t == tx_head) {
        UCSR0B &= (uint8_t)~(1 << UDRIE0);
        return;
    }
    UDR0 = tx_buf[t];
    tx_tail = (uint8_t)(t + 1u);
}

uint8_t uart_frame_ready(void)
{
    return rx_ready;
}

uint8_t uart_frame(const uint8_t **frame)
{
    uint8_t r = rx_ready;
    if (!r) {
        return 0;
    }
    *frame = (const uint8_t *)rx_buf[r - 1u];
    return rx_ready_len;
}

void uart_frame_done(void)
{
    rx_ready = 0;
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
